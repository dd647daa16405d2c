"""Slow motion and time-lapse (processing/frames.py ``filming_clock``): a clip's times are the filming's seconds,
from the phone's tag or from ``video.capture_fps``, so the river's velocity is measured, not the playback's."""

from __future__ import annotations

import pytest

from fieldtool.errors import ParameterError
from fieldtool.processing.frames import FrameSource
from fieldtool.project.model import load_project
from fieldtool.project.validation import validate
from fieldtool.run.pipeline import run_project
from fieldtool.synthetic.retime import replayed


def _q(scene, video: str, **video_keys):
    proj = load_project(scene / "project.toml")
    proj.video.path = video
    for k, v in video_keys.items():
        setattr(proj.video, k, v)
    res = run_project(proj, None)
    return res.discharge.discharge_m3s, res.warnings


def test_a_slow_motion_clip_measures_the_river_at_the_rate_it_was_filmed(scene):
    """The scene's frames played at half their rate: with the phone's tag, or the key, the same discharge as the
    clip at its own rate, and the reason said; without either, half of it (what the file's own clock gives)."""
    q0, _ = _q(scene, "river.mp4")
    replayed(scene / "river.mp4", scene / "tagged.mp4", 2, "30.000000")
    replayed(scene / "river.mp4", scene / "plain.mp4", 2)
    src = FrameSource(scene / "tagged.mp4")
    assert src.time_scale == 0.5 and src.info.fps == 30
    q_tag, said = _q(scene, "tagged.mp4")
    assert q_tag == pytest.approx(q0, rel=1e-9)
    assert any(
        w.startswith("video: filmed at 30 frames per second (the file's com.android.capture.fps tag)") for w in said
    )
    q_plain, said_plain = _q(scene, "plain.mp4")
    assert q_plain == pytest.approx(q0 / 2, rel=0.03) and not any("filmed at" in w for w in said_plain)
    q_key, said_key = _q(scene, "plain.mp4", capture_fps=30.0)
    assert q_key == pytest.approx(q0, rel=1e-9) and any("(video.capture_fps)" in w for w in said_key)


def test_the_filming_clock_sets_the_range_and_refuses_what_it_cannot_apply(scene):
    """``start_s`` and ``end_s`` are the filming's seconds; a tag within 1 % of the file's rate is the file's own
    rate; an image sequence's clock is its frame interval."""
    replayed(scene / "river.mp4", scene / "tagged.mp4", 4, "30.000000")
    whole = FrameSource(scene / "tagged.mp4")
    assert whole.info.duration_s == pytest.approx(1.2, abs=0.05)  # 4.8 s of playback
    part = list(FrameSource(scene / "tagged.mp4", start_s=0.5, end_s=1.0))
    assert part[0].t_s == pytest.approx(0.5, abs=1 / 30) and part[-1].t_s == pytest.approx(1.0, abs=1 / 30)
    replayed(scene / "river.mp4", scene / "same.mp4", 1, "29.97")
    assert FrameSource(scene / "same.mp4").time_scale == 1.0
    (scene / "frames").mkdir()
    with pytest.raises(ParameterError, match="video.capture_fps"):
        FrameSource(scene / "frames", frame_interval_s=0.1, capture_fps=30.0)
    proj = load_project(scene / "project.toml")
    proj.video.capture_fps = float("nan")
    assert any(i.key == "video.capture_fps" for i in validate(proj))
