"""The clip check's frame step (run/clip_check.py over processing/decorrelation.py): what it takes and says."""

from fieldtool.processing.clip_stats import Gates
from fieldtool.processing.decorrelation import Decorrelation
from fieldtool.run import clip_check as cc

SLOW = Decorrelation(tau_frames=12.6, share=0.98, misfit=0.001, frames=20)


def test_the_step_and_its_reason():
    step, said = cc._frame_step(SLOW, 240, None, 30.0)
    assert step == 3 and said.startswith(cc.STEP_LEAD)
    assert "(0.42 s)" in said and "every 3rd frame is used (10 frames per second)" in said
    assert cc._frame_step(Decorrelation(3.3, 0.95, 0.0, 20), 240, None, 30.0) == (1, None)  # the presets' pace
    assert cc._frame_step(Decorrelation(12.6, 0.1, 0.0, 20), 240, None, 30.0) == (1, None)  # noise's fit
    assert cc._frame_step(None, 240, None, 30.0) == (1, None)


def test_no_step_is_said_with_its_reason():
    step, said = cc._frame_step(SLOW, 240, "the frames are stabilised", 30.0)
    assert step == 1 and said.endswith("every frame is used all the same (the frames are stabilised)")
    step, said = cc._frame_step(SLOW, 40, None, 30.0)  # 40 frames cannot keep the 31 of the window at a step of 2
    assert step == 1 and "too short" in said


def test_the_warning_is_the_step_reason_whatever_follows_it():
    """The self-check of ambiguous clips adds its own reason after the step's: the run's warning is the step's
    (it was the last reason, the self-check's, on a faint slow clip)."""
    g = Gates("standard", 3.0, 0.05, None, ["tracer contrast ...", f"{cc.STEP_LEAD} 12.6 frames ...", "ambiguous ..."])
    assert cc.ClipCheck(None, g).step_said == f"{cc.STEP_LEAD} 12.6 frames ..."
    assert cc.ClipCheck(None, Gates("standard", 3.0, 0.05, None, ["tracer contrast ..."])).step_said is None
