"""PyAV's grey frames (processing/video_av.py): the frames and times OpenCV's reader gives, read once per clip."""

import pickle

import cv2
import numpy as np
import pytest

from fieldtool.processing import video_av
from fieldtool.processing.frames import FrameSource, read_color_frame


@pytest.fixture
def textured(tmp_path):
    """A grey clip with a moving random texture (every grey level, codec noise on top)."""
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, (96, 64))
    tex = np.random.default_rng(0).integers(0, 256, (64, 200), dtype=np.uint8)
    for i in range(24):
        g = np.ascontiguousarray(tex[:, 2 * i : 2 * i + 96])
        w.write(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
    w.release()
    return path


def _opencv(path):
    cap = cv2.VideoCapture(str(path))
    out = []
    while cap.grab():
        t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        ok, bgr = cap.retrieve()
        out.append((t, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)))
    cap.release()
    return out


def test_grey_frames_and_times_are_opencvs(textured):
    src = FrameSource(textured)
    got = list(src)
    assert src._av  # read by PyAV, not OpenCV's fallback
    want = _opencv(textured)
    assert len(got) == len(want) == 24
    for f, (t, g) in zip(got, want, strict=True):
        assert f.t_s == pytest.approx(t, abs=1e-9)
        np.testing.assert_array_equal(f.image, g)


def test_unusable_clip_falls_back(tmp_path, textured):
    assert not video_av.usable(str(textured), (65, 96))  # another size than OpenCV's: OpenCV reads it
    assert not video_av.usable(str(tmp_path / "missing.mp4"), (64, 96))


def test_head_is_replayed_without_a_second_decode(textured, monkeypatch):
    src = FrameSource(textured)
    whole = [(f.t_s, f.image.copy()) for f in src]
    opened = []
    orig = video_av.open_clip
    monkeypatch.setattr(video_av, "open_clip", lambda *a: opened.append(1) or orig(*a))
    head = src.head(5)
    assert len(head) == 5 and len(opened) == 1
    later = list(src.iter_wanted(lambda k: k % 2 == 0))  # the pass after the look continues its decoder
    assert len(opened) == 1 and len(later) == len(whole)
    for k, (f, (t, img)) in enumerate(zip(later, whole, strict=True)):
        assert f.t_s == t
        if k % 2:
            assert f.image is None
        else:
            np.testing.assert_array_equal(f.image, img)
    assert len(list(src)) == len(whole) and len(opened) == 2  # a pass after that decodes again


def test_a_source_with_a_head_still_goes_to_the_figure_process(textured):
    """The run's inputs go to the figure process as a pickle; the head's open decoder stays behind (it made the
    pickle fail, and the run drew every figure itself)."""
    src = FrameSource(textured)
    src.head(3)
    copy = pickle.loads(pickle.dumps(src))
    assert len(list(copy)) == 24  # a pass of its own
    assert len(list(src)) == 24  # the original still replays its head


def test_frames_read_in_a_region_are_right_there_and_zero_elsewhere(textured):
    """``iter_wanted(want, region)``: only the region is converted to grey (the run's standardisation box and
    STIV's lines at 4K are a tenth of the frame); outside it the frame is 0, and nobody can write into it."""
    whole = [f.image.copy() for f in FrameSource(textured)]
    region = (10, 20, 50, 44)
    x0, y0, x1, y1 = region
    got = list(FrameSource(textured).iter_wanted(None, region))
    assert len(got) == len(whole)
    for f, img in zip(got, whole, strict=True):
        np.testing.assert_array_equal(f.image[y0:y1, x0:x1], img[y0:y1, x0:x1])
        outside = f.image.copy()
        outside[y0:y1, x0:x1] = 0
        assert not outside.any() and img[:y0].any()  # the frame had texture there, the region's frame has none
        with pytest.raises(ValueError):
            f.image[0, 0] = 1  # read-only: a recycled frame stays 0 outside its region


def test_a_head_read_in_a_region_is_replayed_only_for_a_region_inside_it(textured, monkeypatch):
    """The clip check's look at the first frames and the run's pass share one decode when they read the same
    box; a pass that wants more of the frame than the look converted decodes again (frames are never
    handed out wrong)."""
    whole = [f.image.copy() for f in FrameSource(textured)]
    opened = []
    orig = video_av.open_clip
    monkeypatch.setattr(video_av, "open_clip", lambda *a: opened.append(1) or orig(*a))
    src = FrameSource(textured)
    src.head(5, (10, 20, 50, 44))
    inner = list(src.iter_wanted(None, (12, 22, 40, 40)))
    assert len(opened) == 1 and len(inner) == len(whole)
    np.testing.assert_array_equal(inner[3].image[22:40, 12:40], whole[3][22:40, 12:40])
    src.head(5, (10, 20, 50, 44))
    full = list(src)  # the whole frame: a pass of its own
    assert len(opened) == 3
    for f, img in zip(full, whole, strict=True):
        np.testing.assert_array_equal(f.image, img)


def test_one_clip_read_in_two_regions_gives_frames_zero_outside_each(textured):
    """A recycled frame is 0 outside the region it was made for: a clip asked for another region hands out
    frames of their own, never one that still holds the first region's grey levels."""
    clip = video_av.open_clip(str(textured), 1)
    try:
        a, b = (10, 20, 50, 44), (60, 0, 90, 30)
        held = []
        for k, (_, fr) in enumerate(clip.decoded()):
            region = a if k < 6 else b
            img = clip.grey(fr, region)
            outside = img.copy()
            outside[region[1] : region[3], region[0] : region[2]] = 0
            assert not outside.any(), k
            if k < 6:
                del img  # frames of region a go back to their pool
            else:
                held.append(img)
            if k == 11:
                break
    finally:
        clip.close()


@pytest.mark.parametrize("av_reader", [True, False])
def test_a_watched_clip_keeps_the_patches_of_its_first_frames_then_every_few(textured, monkeypatch, av_reader):
    """``watch(boxes, first, every)``: every pass keeps the grey crops of the boxes (the camera check's patches
    around the GCPs, run/camera.py) for the first frames and every few after, outside its region too, by PyAV and
    by OpenCV's reader; a second look at the head for a region inside it
    decodes nothing again, and the pass that continues it is the one decode of the clip."""
    whole = [f.image.copy() for f in FrameSource(textured)]
    opened = []
    orig = video_av.open_clip
    monkeypatch.setattr(video_av, "open_clip", lambda *a: opened.append(1) or orig(*a))
    src = FrameSource(textured)
    if not av_reader:
        src._av = False
    region, boxes = (10, 20, 50, 44), [(60, 2, 90, 30), (0, 40, 20, 60)]
    src.watch(boxes, first=5, every=4)
    head = src.head(5, region)
    assert sorted(src.watched) == [0, 1, 2, 3, 4]
    again = src.head(5, (12, 22, 40, 40))
    assert [f.t_s for f in again] == [f.t_s for f in head] and len(opened) == (1 if av_reader else 0)
    rest = list(src.iter_wanted(lambda k: k % 3 == 0, region))
    assert len(rest) == len(whole) and len(opened) == (1 if av_reader else 0)
    kept = [k for k in range(24) if k < 5 or k % 4 == 0]  # the pass continues the head's decoder: all converted
    assert sorted(src.watched) == kept
    for k in kept:
        t, crops = src.watched[k]
        assert t == pytest.approx(rest[k].t_s)
        for (x0, y0, x1, y1), c in zip(boxes, crops, strict=True):
            np.testing.assert_array_equal(c, whole[k][y0:y1, x0:x1])
    copy = pickle.loads(pickle.dumps(src))  # the figure process' copy leaves the crops behind
    assert copy.watched == {} and copy._watch is None
    src.watch(None)
    assert src.watched == {} and src._watched(0) is None


def test_a_thinned_source_replays_every_nth_frame_of_its_head_and_goes_on(textured, monkeypatch):
    """The run looks at the first frames at the clip's own rate and may then use every n-th frame
    (``FrameSource.thin``, processing/decorrelation.py): the pass replays the head's frames on the new step and
    continues their decoder, giving the frames a source made with that step gives, decoded once."""
    want = [(f.t_s, f.image.copy()) for f in FrameSource(textured, step=3)]
    opened = []
    orig = video_av.open_clip
    monkeypatch.setattr(video_av, "open_clip", lambda *a: opened.append(1) or orig(*a))
    src = FrameSource(textured)
    n = src.estimated_count()
    assert len(src.head(10)) == 10
    src.thin(3)
    assert src.step == 3 and src.estimated_count() == -(-n // 3)
    got = list(src.iter_wanted(lambda k: k != 2))
    assert len(opened) == 1 and len(got) == len(want) == 8
    for k, (f, (t, img)) in enumerate(zip(got, want, strict=True)):
        assert f.t_s == t
        if k == 2:
            assert f.image is None
        else:
            np.testing.assert_array_equal(f.image, img)
    src.thin(1)  # no change
    assert src.step == 3


@pytest.mark.parametrize("av_reader", [True, False])
def test_a_thinned_watch_keeps_its_patches_over_the_same_seconds(textured, av_reader):
    """After ``thin(n)`` the watch counts the new step's frames: the patches of the head's kept frames under their
    new numbers, then the first and every few re-counted, so the camera's later check (run/camera.py) sees as much
    of the clip, in seconds, as without the step, and no patch sits under another frame's number."""
    whole = [(f.t_s, f.image.copy()) for f in FrameSource(textured)]
    src = FrameSource(textured)
    if not av_reader:
        src._av = False
    boxes = [(60, 2, 90, 30)]
    src.watch(boxes, first=4, every=5)
    src.head(8)
    assert sorted(src.watched) == [0, 1, 2, 3, 5]
    src.thin(2)
    assert src.watch_first == 2 and sorted(src.watched) == [0, 1]  # frames 0 and 2
    list(src)
    kept = sorted(src.watched)
    assert kept == [0, 1, 6, 9]  # the head's frames 0 and 2, then every 6th frame after the head: 12, 18
    for k in kept:
        t, crops = src.watched[k]
        assert t == pytest.approx(whole[2 * k][0])
        np.testing.assert_array_equal(crops[0], whole[2 * k][1][2:30, 60:90])


def _deep_clip(path, codec, fmt, n=12):
    """A 10-bit clip (``codec``, pixel format ``fmt``) of a moving texture, written by PyAV; None where this
    FFmpeg has no such encoder."""
    import av

    try:
        av.codec.Codec(codec, "w")
    except av.codec.codec.UnknownCodecError:
        return None
    tex = np.random.default_rng(3).integers(0, 256, (64, 140), dtype=np.uint8)
    with av.open(str(path), "w") as out:
        st = out.add_stream(codec, rate=30, options={"x265-params": "log-level=error"} if "265" in codec else {})
        st.width, st.height, st.pix_fmt = 96, 64, fmt
        for i in range(n):
            g = np.ascontiguousarray(tex[:, 3 * i : 3 * i + 96])
            frame = av.VideoFrame.from_ndarray(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), format="bgr24").reformat(format=fmt)
            frame.pts = i
            for pk in st.encode(frame):
                out.mux(pk)
        for pk in st.encode():
            out.mux(pk)
    return path


@pytest.mark.parametrize("codec, fmt, ext", [("libx265", "yuv420p10le", "mp4"), ("prores_ks", "yuv422p10le", "mov")])
def test_a_ten_bit_clip_is_read_by_pyav_through_a_table_of_its_levels(tmp_path, codec, fmt, ext):
    """An iPhone's HDR HEVC or a ProRes clip (10-bit planes): read by PyAV, its grey frames FFmpeg's own grey of
    every frame (a table of 1024 levels), its region the whole frame's box, its colour frame FFmpeg's BGR; OpenCV's
    BGR of such a frame costs 45 ms a 720p frame (2 s for the first) and saturates the highlights of HLG."""
    import av

    path = _deep_clip(tmp_path / f"clip.{ext}", codec, fmt)
    if path is None:
        pytest.skip(f"no {codec} encoder in this FFmpeg")
    with av.open(str(path)) as c:
        want = [f.to_ndarray(format="gray") for f in c.decode(c.streams.video[0])]
        assert c.streams.video[0].codec_context.pix_fmt == fmt
    src = FrameSource(path)
    got = [f.image for f in src]
    assert src._av and len(got) == len(want) == 12
    for g, w in zip(got, want, strict=True):
        assert g.dtype == np.uint8 and np.abs(g.astype(int) - w.astype(int)).max() <= 1
    box = (10, 8, 70, 50)
    part = [f.image for f in FrameSource(path).iter_wanted(lambda k: True, box)]
    np.testing.assert_array_equal(part[5][8:50, 10:70], got[5][8:50, 10:70])
    with av.open(str(path)) as c:
        colour = next(c.decode(c.streams.video[0])).to_ndarray(format="bgr24")
    np.testing.assert_array_equal(read_color_frame(path), colour)
    assert video_av.deep_frame(str(tmp_path / "none.mp4")) is None
