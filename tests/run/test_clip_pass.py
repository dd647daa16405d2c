"""One decode per clip (run/clip_pass.py): the rounds of pairs replay the frames round 1's pass kept, and
give the field a new pass would."""

from __future__ import annotations

import numpy as np
import pytest

from fieldtool.processing import video_av
from fieldtool.processing.frames import FrameSource
from fieldtool.project.model import load_project
from fieldtool.run import clip_pass
from fieldtool.run import frames as frames_mod
from fieldtool.run.pipeline import run_project


def _stream(n: int, shape=(40, 60), box=(10, 5, 50, 30)):
    """Frames that are 0 outside ``box``, as the standardisation's are, with their times."""
    rng = np.random.default_rng(1)
    for k in range(n):
        img = np.zeros(shape, np.float32)
        x0, y0, x1, y1 = box
        img[y0:y1, x0:x1] = rng.standard_normal((y1 - y0, x1 - x0)).astype(np.float32)
        yield 0.1 * k, img


def test_raw_boxes_replay_every_frame_as_the_standardisation_read_it():
    """With the standardisation, every frame's raw box is kept and replayed whole (0 outside the box), for the
    standardisation to run on again."""
    frames = list(_stream(12))
    kept = clip_pass.KeptFrames((40, 60), (10, 5, 50, 30))
    kept.plan(n_frames=12, n_pairs_total=11, first_round=2, gap=1, bytes_per_px=4)
    assert not kept.wants(3)  # nothing to build for the keeping
    got = list(kept.keeping(iter(frames)))
    assert [t for t, _ in got] == [t for t, _ in frames]  # the stream passes unchanged
    replay = list(kept.replay(lambda k: k == 3))  # every frame, whatever the round wants: the window needs them
    assert len(replay) == 12
    for k, (t, img) in enumerate(replay):
        assert t == frames[k][0]
        assert np.array_equal(img, frames[k][1]) and not img.flags.writeable


def test_raw_boxes_all_or_none():
    box = (10, 5, 50, 30)
    kept = clip_pass.KeptFrames((40, 60), box, budget_bytes=11 * 40 * 25 * 4)  # 11 boxes of float32
    kept.plan(n_frames=12, n_pairs_total=11, first_round=2, gap=1, bytes_per_px=4)
    assert kept.full and kept.replay(lambda k: True) is None  # the clip does not fit: nothing kept
    kept = clip_pass.KeptFrames((40, 60), box, budget_bytes=11 * 40 * 25 * 4)
    kept.plan(n_frames=10, n_pairs_total=9, first_round=2, gap=1, bytes_per_px=4)  # the container says 10
    assert not kept.full
    list(kept.keeping(_stream(12)))  # but 12 come: dropped when the budget ran out
    assert kept.full and not kept.frames and kept.replay(lambda k: True) is None


def test_replay_gives_the_kept_frames_and_none_where_not_wanted():
    frames = list(_stream(12))
    kept = clip_pass.KeptFrames((40, 60))
    kept.plan(n_frames=12, n_pairs_total=11, first_round=2, gap=1, bytes_per_px=4)
    got = list(kept.keeping(iter(frames)))
    assert [t for t, _ in got] == [t for t, _ in frames]  # the stream passes unchanged
    want = {k for k in range(12) if kept.wants(k)}
    replay = list(kept.replay(want.__contains__))
    assert len(replay) == 12
    for k, (t, img) in enumerate(replay):
        assert t == frames[k][0]
        if k in want:
            assert np.array_equal(img, frames[k][1]) and img.flags.writeable  # a fresh frame, as a new pass builds
        else:
            assert img is None


def test_replay_refuses_a_frame_not_kept_and_an_unfinished_pass():
    kept = clip_pass.KeptFrames((40, 60), budget_bytes=3 * 40 * 60 * 4)  # three frames
    kept.plan(n_frames=12, n_pairs_total=11, first_round=0, gap=1, bytes_per_px=4)
    assert sum(kept.wants(k) for k in range(12)) <= 3 + 1  # the budget, and position 0
    it = kept.keeping(_stream(12))
    next(it)
    assert kept.replay(lambda k: k == 0) is None  # the pass has not reached the clip's end
    list(it)
    assert kept.replay(lambda k: True) is None  # a wanted frame was not kept: the round reads the clip again
    assert kept.replay(lambda k: k == 0) is not None


@pytest.mark.parametrize("standardize", [True, False])
def test_rounds_decode_each_frame_once_and_match_a_new_pass(scene, monkeypatch, standardize):
    proj = load_project(scene / "project.toml")
    proj.piv.min_pairs = 4
    proj.piv.frame_gap = 1
    proj.piv.converge_rel_ci = 1e-6  # never converged: rounds until every pair is in
    proj.piv.remove_stationary = standardize
    one = run_project(proj, None)
    s = one.summary()["piv_sampling"]
    assert s["rounds"] >= 2
    assert s["frames_decoded"] == s["frames_in_range"] == 36  # one pass: the later rounds replay its frames
    monkeypatch.setattr(clip_pass, "KEEP_BYTES", 0)  # nothing kept: each round reads the clip again
    again = run_project(proj, None)
    s2 = again.summary()["piv_sampling"]
    assert s2["rounds"] == s["rounds"] and s2["frames_in_range"] == 36
    assert s2["frames_decoded"] >= 2 * 36 - 1  # round 2 reads the clip again (up to its last pair)
    # the replayed frames are those a new pass builds: the same field, the same discharge
    assert np.array_equal(one.piv.u, again.piv.u, equal_nan=True)
    assert one.discharge.discharge_m3s == again.discharge.discharge_m3s


def test_frames_converted_only_in_the_read_region_give_the_whole_frames_field(scene, monkeypatch):
    """The run converts only the box its consumers read (the standardisation's and STIV's lines): the same
    field, STIV and discharge as from whole frames, and one decode of the clip."""
    proj = load_project(scene / "project.toml")
    regions = []
    orig = video_av.Clip.grey
    monkeypatch.setattr(
        video_av.Clip, "grey", lambda self, fr, region=None: regions.append(region) or orig(self, fr, region)
    )
    boxed = run_project(proj, None)
    read = {r for r in regions if r is not None}
    assert len(read) == 1 and None not in regions  # every frame of the run's pass read in one box
    x0, y0, x1, y1 = read.pop()
    h, w = FrameSource(scene / proj.video.path).shape
    assert (x1 - x0) * (y1 - y0) < 0.8 * h * w  # less than the frame
    assert boxed.summary()["piv_sampling"]["frames_decoded"] == 36
    monkeypatch.setattr(frames_mod, "in_region_ok", lambda *a: False)
    regions.clear()
    whole = run_project(proj, None)
    assert set(regions) == {None}
    assert np.array_equal(boxed.piv.u, whole.piv.u, equal_nan=True)
    assert boxed.discharge.discharge_m3s == whole.discharge.discharge_m3s
    untimed = lambda r: {k: v for k, v in r.summary()["stiv"].items() if k != "seconds"}  # noqa: E731
    assert untimed(boxed) == untimed(whole)


def test_budget_shrinks_with_the_frame_size_beyond_1080p():
    small, hd, fhd, uhd = (clip_pass.budget(s) for s in ((48, 64), (720, 1280), (1080, 1920), (2160, 3840)))
    assert small == hd == fhd == clip_pass.KEEP_BYTES  # up to 1080p: the whole budget (round 2 replayed as before)
    assert uhd == clip_pass.KEEP_BYTES - clip_pass.PER_PX_BYTES * (2160 * 3840 - 1920 * 1080) < 150 * 2**20
    assert clip_pass.budget((20000, 20000)) == clip_pass.KEEP_BYTES // 4


def test_decoding_in_a_thread_of_its_own_gives_the_same_field(scene, monkeypatch):
    """Where decoding the frame costs more than standardising its box (a 4K clip, a narrow band), the decoding
    runs in a thread of its own: the same field and discharge, one decode of the clip."""
    from fieldtool.run import velocimetry

    assert velocimetry.decode_bound((2160, 3840), (1726, 88, 2114, 2072))  # 4K, the section's band: 388 px wide
    assert not velocimetry.decode_bound((720, 1280), (503, 12, 1093, 689))  # 720p: 45 % of the frame
    proj = load_project(scene / "project.toml")
    one = run_project(proj, None)
    calls = []
    monkeypatch.setattr(velocimetry, "decode_bound", lambda shape, box: calls.append(box) or True)
    split = run_project(proj, None)
    assert calls  # the run asked, and split its reading
    assert split.summary()["piv_sampling"]["frames_decoded"] == one.summary()["piv_sampling"]["frames_decoded"]
    assert np.array_equal(one.piv.u, split.piv.u, equal_nan=True)
    assert one.discharge.discharge_m3s == split.discharge.discharge_m3s
