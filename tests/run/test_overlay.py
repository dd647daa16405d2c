"""The overlay video (overlay.mp4, ``fieldtool run --overlay``): frames and times of the analysed range, H.264
yuv420p that PyAV and chromium read, vectors drawn in the colour map inside the section's band, no file
without the option, no second decode of the clip, the report's <video>, the rerun stream and the TUI key."""

import argparse
import asyncio
import shutil
import sys

import av
import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from fieldtool.processing.frames import FrameSource
from fieldtool.project.model import load_project
from fieldtool.project.validation import validate
from fieldtool.records.report import write_report
from fieldtool.run import clip_check, overlay_stage
from fieldtool.run.pipeline import run_project
from fieldtool.viewer.rerun_log import observer_from_args
from fieldtool.writers import overlay as draw

CARD_S = 2.0  # the default [overlay] card_s: the closing card's frames follow the clip's


def _count_passes(monkeypatch):
    """Count the passes over the clip (each one a decode of its frames from the start) that read more than the
    clip check's look at the first frames (run/clip_check.py: N_FRAMES frames, before any pass of the run)."""
    passes: list[bool] = []
    orig = FrameSource._iter_video

    def counted(self, want=None, region=None):
        n = 0
        for item in orig(self, want, region):
            n += 1
            if n == clip_check.N_FRAMES + 1:
                passes.append(want is None)
            yield item

    monkeypatch.setattr(FrameSource, "_iter_video", counted)
    return passes


@pytest.fixture(scope="module")
def runs(short_scene, tmp_path_factory):
    """Five runs of the 1.2 s oblique scene: plain; overlay into the same folder (PIV field reused); overlay in a
    fresh folder with the rerun stream beside it (whole clip: the stationary-pattern removal's path); overlay of
    0.2-1.0 s (too short for that removal: the fast path that builds only its pairs' frames); the rectified view
    at half the clip's rate."""
    root = tmp_path_factory.mktemp("overlay")
    for f in short_scene.project_path.parent.iterdir():
        if f.is_file():
            shutil.copy(f, root / f.name)
    mp = pytest.MonkeyPatch()
    out = {}
    try:
        for name, overlay, folder, rerun, rng in (
            ("plain", False, "a", False, None),
            ("cached", True, "a", False, None),
            ("streamed", True, "c", True, None),
            ("range", True, "d", False, (0.2, 1.0)),
            ("rectified", True, "e", False, None),
        ):
            p = load_project(root / "project.toml")
            p.overlay.enabled = overlay
            if name == "rectified":  # the map view at half the clip's rate, 640 px, a 0.5 s card
                p.overlay.view, p.overlay.fps, p.overlay.width_px, p.overlay.card_s = "rectified", 15.0, 640, 0.5
            if rng:
                p.video.start_s, p.video.end_s = rng
            obs = (
                observer_from_args(p, argparse.Namespace(rerun="save", rerun_path=None, rerun_url=None), root / folder)
                if rerun
                else None
            )
            passes = _count_passes(mp)
            res = run_project(p, root / folder, observer=obs)
            mp.undo()
            out[name] = (p, res, root / folder, list(passes), (root / folder / "overlay.mp4").exists())
    finally:
        mp.undo()
    return out


def _decode(path):
    with av.open(str(path)) as c:
        st = c.streams.video[0]
        meta = (st.codec_context.name, st.codec_context.pix_fmt, st.width, st.height, float(st.average_rate))
        frames = [(float(f.time), f.to_ndarray(format="bgr24")) for f in c.decode(video=0)]
    return meta, frames


def _analysed(project):
    v = project.video
    return list(FrameSource(project.resolve(v.path), v.start_s, v.end_s, v.step, v.frame_interval_s))


def test_a_plain_run_writes_no_overlay(runs):
    p, res, out, _, exists = runs["plain"]
    assert not exists  # (looked at before the next run wrote one into the same folder)
    assert "overlay" not in res.files and res.summary()["overlay"] is None


@pytest.mark.parametrize("name", ["cached", "streamed", "range"])
def test_frames_and_times_match_the_analysed_range(runs, name):
    p, res, out, *_ = runs[name]
    assert res.files.get("overlay") == "overlay.mp4", res.warnings
    (codec, pix, w, h, fps), frames = _decode(out / "overlay.mp4")
    assert (codec, pix) == ("h264", "yuv420p") and w % 2 == 0 and h % 2 == 0
    expected = _analysed(p)
    n_card = int(round(CARD_S * fps))
    assert len(frames) == len(expected) + n_card
    t0 = expected[0].t_s
    got = np.array([t for t, _ in frames[: len(expected)]])
    want = np.array([f.t_s - t0 for f in expected])
    assert np.max(np.abs(got - want)) < 0.5 / fps
    card = np.array([t for t, _ in frames[len(expected) :]])
    assert np.allclose(np.diff(card), 1.0 / fps, atol=1e-6) and card[0] > got[-1]
    info = res.summary()["overlay"]
    assert info["frames"] == len(expected) and info["card_frames"] == n_card
    assert info["t_first_s"] == pytest.approx(expected[0].t_s) and info["t_last_s"] == pytest.approx(expected[-1].t_s)
    assert info["pairs_drawn"] >= 2
    data = (out / "overlay.mp4").read_bytes()
    assert 0 < data.find(b"moov") < data.find(b"mdat")  # +faststart: a browser plays it while it loads


def test_rectified_view_at_half_the_rate(runs):
    p, res, out, *_ = runs["rectified"]
    (codec, pix, w, h, fps), frames = _decode(out / "overlay.mp4")
    assert fps == 15.0 and w <= 640 and (w % 2, h % 2) == (0, 0) and codec == "h264"
    kept = _analysed(p)[::2]  # 30 fps clip, 15 fps video: every second frame, at its own time
    n_card = int(round(0.5 * fps))
    assert len(frames) == len(kept) + n_card
    got = np.array([t for t, _ in frames[: len(kept)]])
    assert np.max(np.abs(got - np.array([f.t_s - kept[0].t_s for f in kept]))) < 0.25 / fps
    mid = frames[len(kept) // 2][1].astype(int)
    assert ((mid.max(axis=2) - mid.min(axis=2)) > 40).sum() > 300  # vectors and section on the map
    assert res.summary()["overlay"]["view"] == "rectified"


def test_no_second_decode_of_the_clip(runs):
    """The overlay takes the run's own frames: as many passes over the clip as the plain run; a run that
    reuses its PIV field makes one pass (STIV's lines and the overlay share it)."""
    assert len(runs["streamed"][3]) == len(runs["plain"][3])
    assert runs["cached"][1].piv_reused and len(runs["cached"][3]) == 1


def test_vectors_are_drawn_in_the_colour_map_inside_the_band(runs):
    p, res, out, *_ = runs["streamed"]
    (_, _, w, h, _), frames = _decode(out / "overlay.mp4")
    expected = _analysed(p)
    k = len(expected) // 2
    drawn = frames[k][1].astype(int)
    raw = cv2.cvtColor(overlay_stage.downscale(expected[k].image, (w, h)), cv2.COLOR_GRAY2BGR)
    sx, sy = w / expected[k].image.shape[1], h / expected[k].image.shape[0]
    seg = np.asarray(res.section.p_img, float) * (sx, sy)
    band = np.zeros((h, w), np.uint8)
    cv2.line(band, tuple(int(v) for v in seg[0]), tuple(int(v) for v in seg[1]), 255, int(0.08 * h))
    band = band > 0
    colourful = (drawn.max(axis=2) - drawn.min(axis=2)) > 40  # the clip is gray: colour is what was drawn
    assert not ((raw.max(axis=2).astype(int) - raw.min(axis=2)) > 40).any()
    inside = colourful & band
    assert inside.sum() > 300, inside.sum()
    table = draw.lut("viridis").astype(int)
    # thin anti-aliased arrows blend the map's colour with the gray clip, which keeps its chroma's direction
    px = drawn[inside].astype(float)
    c = px - px.mean(axis=1, keepdims=True)
    lc = table - table.mean(axis=1, keepdims=True)
    cos = (c @ lc.T) / (np.linalg.norm(c, axis=1)[:, None] * np.linalg.norm(lc, axis=1)[None, :] + 1e-9)
    assert np.mean(cos.max(axis=1) > 0.9) > 0.8
    # away from the band, the legend and the text boxes the frame is the clip's (up to the encoder's error)
    far = np.zeros((h, w), bool)
    far[int(0.62 * h) : int(0.85 * h), int(0.72 * w) : int(0.97 * w)] = True
    far &= ~cv2.dilate(band.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool)
    assert far.sum() > 1000
    assert np.mean(np.abs(drawn[far] - raw[far].astype(int))) < 8


def test_report_and_rerun_carry_the_video(runs):
    p, res, out, *_ = runs["streamed"]
    (html_path,) = write_report(out)
    text = html_path.read_text()
    assert "<video id='overlay-video'" in text and "src='data:video/mp4;base64," in text
    ent = {}
    for ch in RrdReader(out / "run.rrd").stream():
        ent.setdefault(ch.entity_path, []).append(ch.to_record_batch())
    assert "/overlay/video" in ent
    logs = [v for rb in ent["/log"] if "TextLog:text" in rb.schema.names for v in rb.column("TextLog:text").to_pylist()]
    assert any("overlay video:" in str(t) and "overlay.mp4" in str(t) for t in logs)
    assert not [w for w in res.warnings if "overlay" in w or "rerun" in w]


def test_the_lut_and_the_writer_fallback(tmp_path, monkeypatch):
    table = draw.lut("viridis")
    assert table.shape == (256, 3)
    lum = table[:, ::-1].astype(float) @ [0.2126, 0.7152, 0.0722]
    assert np.all(np.diff(lum) > -1.0)  # perceptual: luminance rises along the map
    c = draw.colours([np.nan, 0.0, 5.0], 0.0, 1.0, table)
    assert tuple(c[0]) == draw.NO_VALUE_BGR and tuple(c[1]) == tuple(table[0]) and tuple(c[2]) == tuple(table[-1])
    assert [draw.nice_ceil(x) for x in (0.93, 1.3, 1.51, 7.0)] == [1.0, 1.5, 2.0, 8.0]
    monkeypatch.setitem(sys.modules, "av", None)  # `import av` raises ImportError: the OpenCV fallback
    w = draw.VideoWriter(tmp_path / "x.mp4", 64, 48, 10)
    assert w.backend == "opencv" and "pip install av" in w.warning
    for k in range(5):
        w.write(np.full((48, 64, 3), 40 * k, np.uint8), k)
    w.close()
    cap = cv2.VideoCapture(str(tmp_path / "x.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    cap.release()
    with pytest.raises(ValueError):
        draw.VideoWriter(tmp_path / "odd.mp4", 63, 48, 10)


def test_overlay_keys_are_validated(short_scene):
    p = load_project(short_scene.project_path)
    p.overlay.width_px = 100
    p.overlay.view = "sideways"
    keys = {pr.key for pr in validate(p, files=False) if pr.severity == "error"}
    assert {"overlay.width_px", "overlay.view"} <= keys


def test_a_failing_observer_leaves_the_others_running():
    calls, warnings = [], []

    class Bad:
        def pair(self, *a):
            raise RuntimeError("boom")

    class Good:
        def pair(self, *a):
            calls.append(a)

    fan = overlay_stage.Fanout([Bad(), Good()], warnings)
    fan.pair(1)
    fan.pair(2)
    fan.stage("x")  # a method no observer has is skipped
    assert calls == [(1,), (2,)] and len(warnings) == 1 and "boom" in warnings[0]
    assert overlay_stage.fan_out(None, None, warnings) is None


def test_tui_ctrl_g_renders_the_overlay(tmp_path, monkeypatch):
    """ctrl+l on the results step runs the project again with [overlay] enabled for that run only."""
    from test_tui_snapshots import fake_result, make_project

    from fieldtool.tui import jobs
    from fieldtool.tui.app import FieldToolApp

    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p)
    seen = []
    monkeypatch.setattr(jobs, "run_full", lambda project, out, job: seen.append(project.overlay.enabled) or {})

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=(80, 24)) as pilot:
            await pilot.pause(0.3)
            assert "ctrl+l renders the overlay video" in str(app.screen.query_one("#files").render())
            await pilot.press("ctrl+l")
            for _ in range(50):
                if seen:
                    break
                await pilot.pause(0.1)
            assert seen == [True]
            assert app.session.project.overlay.enabled is False  # the project itself is unchanged

    asyncio.run(go())


@pytest.mark.browser
def test_chromium_plays_the_reports_video(runs, tmp_path):
    """The report's <video> in Debian's chromium: it loads, seeks and shows the drawn (coloured) frame."""
    from chromium_setup import LAUNCH_ARGS, ensure_chromium

    path, reason = ensure_chromium()
    if path is None:
        pytest.skip(f"chromium unavailable: {reason}")
    playwright = pytest.importorskip("playwright.sync_api")
    p, res, out, *_ = runs["streamed"]
    (html_path,) = write_report(out, tmp_path / "report.html")
    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(path), args=LAUNCH_ARGS)
        try:
            page = browser.new_page()
            page.goto(html_path.as_uri())
            page.wait_for_function("() => document.querySelector('#overlay-video').readyState >= 1", timeout=30000)
            info = page.evaluate(SEEK_AND_COUNT, 0.5)
        finally:
            browser.close()
    ov = res.summary()["overlay"]
    assert info["err"] is None and (info["w"], info["h"]) == (ov["width_px"], ov["height_px"])
    assert info["duration"] == pytest.approx((ov["frames"] + ov["card_frames"]) / ov["fps"], abs=0.1)
    assert info["colourful"] > 300  # vectors and section in colour on the gray clip


SEEK_AND_COUNT = """(t) => new Promise(res => { const v = document.querySelector('#overlay-video');
  v.addEventListener('seeked', () => { const c = document.createElement('canvas'); c.width = v.videoWidth;
    c.height = v.videoHeight; const g = c.getContext('2d'); g.drawImage(v, 0, 0);
    const d = g.getImageData(0, 0, c.width, c.height).data; let col = 0;
    for (let i = 0; i < d.length; i += 4) {
      if (Math.max(d[i], d[i+1], d[i+2]) - Math.min(d[i], d[i+1], d[i+2]) > 40) col++; }
    res({w: v.videoWidth, h: v.videoHeight, duration: v.duration, colourful: col, err: v.error && v.error.code}); },
    {once: true});
  v.currentTime = t; })"""


def test_a_cancelled_run_leaves_no_partial_video(short_scene, tmp_path, monkeypatch):
    import tempfile

    from fieldtool.errors import Cancelled

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    p = load_project(short_scene.project_path)
    p.overlay.enabled = True
    seen = []

    def cancel():
        seen.append(1)
        return len(seen) > 20

    with pytest.raises(Cancelled):
        run_project(p, tmp_path / "out", cancel=cancel)
    assert list((tmp_path / "tmp").iterdir()) == [] and not (tmp_path / "out" / "overlay.mp4").exists()
