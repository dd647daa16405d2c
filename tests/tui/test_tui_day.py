"""The operator's day at 80 x 24 (issue 25, item 5): what was missing or wrong on the screen, one test each."""

import asyncio
import io
import json
import re

from test_tui_layout import screen_lines
from test_tui_snapshots import SIZE, fake_result, make_project

from fieldtool.project.model import load_project
from fieldtool.tui.app import FieldToolApp
from fieldtool.tui.fields import Field
from fieldtool.tui.widgets.field_row import FieldRow


def run(coro):
    return asyncio.run(coro)


def _row(app, key):
    return next(r for r in app.screen.query(FieldRow) if r.field.key == key)


def _text(app) -> str:
    return "\n".join(screen_lines(app))


def test_discharge_step_has_the_measurement_fields_and_a_report_action(tmp_path):
    """Defect: no fields for name, site, station, operator and no report action: a TUI-only report read
    "measurement" with "–" for site, station and operator."""
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p)

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            for key, value in (
                ("name", "Meuse at Lixhe 2026-12-01"),
                ("site", "lixhe"),
                ("station", "L-7396"),
                ("operator", "A. Hydro"),
            ):
                _row(app, key).control.value = value
                await pilot.pause()
            assert app.session.result_state()[0] == "current"  # typing them does not make the result stale
            await pilot.press("ctrl+g")
            await pilot.pause(0.5)
            assert "report.pdf" in app.status[0] and not app.status[1], app.status

    run(go())
    saved = load_project(tmp_path / "m" / "project.toml")
    assert (saved.site, saved.station, saved.operator) == ("lixhe", "L-7396", "A. Hydro")
    html = (tmp_path / "m" / "out" / "report.html").read_text()
    head = html[html.index("id='header'") : html.index("id='discharge'")]
    assert "Meuse at Lixhe 2026-12-01" in html and "lixhe" in head and "L-7396" in head and "A. Hydro" in head
    assert (tmp_path / "m" / "out" / "report.pdf").read_bytes().startswith(b"%PDF")


def test_run_warnings_are_next_to_q_on_the_first_screen(tmp_path):
    """Defect: the run's warnings on the discharge step were below the fold, with nothing saying so."""
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p, n=15, quality=True)
    rj = tmp_path / "m" / "out" / "result.json"
    s = json.loads(rj.read_text())
    s["warnings"] = ["level is 3 cm above the survey's highest point", "second warning"]
    s["stiv"] = {"velocity_source": "auto", "velocity_source_used": "combined", "discharge_piv_m3s": 1.25}
    rj.write_text(json.dumps(s))

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            text = " ".join(ln[24:].strip() for ln in screen_lines(app))
            assert "2 warnings (in full below the table): level is" in text, text
            assert "discharge      1.2345 m³/s" in text
            assert "alpha 0.80 default from PIV+STIV" in " ".join(text.split()), text

    run(go())


def test_step_one_does_not_start_with_file_not_found(tmp_path):
    """Defect: step 1 of a fresh project said "cross-section file not found" before anything was typed."""
    from fieldtool.project.template import write_template

    path = write_template(tmp_path)

    async def go():
        app = FieldToolApp(path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            text = _text(app)
            assert "not found" not in text, text
            assert "no cross-section yet" in text

    run(go())


def test_filter_example_agrees_with_the_default(tmp_path):
    """Defect: the parameters field said "e.g. clip_limit=2.0" beside "clip_limit (default 40)"."""
    from textual.widgets import Input

    make_project(tmp_path / "m", "filters")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            ph = app.screen.query_one("#filter-params", Input).placeholder
            assert "clip_limit=40" in ph and "2.0" not in ph, ph
            assert "default 40" in _text(app)

    run(go())


def test_picked_pixels_show_two_decimals_and_keep_their_digits(tmp_path):
    """Defect: a snapped pick showed 16 decimals and was cut at 80 columns. The field shows 2 decimals; the
    file keeps the snapped centre exactly (showing it is not an edit)."""
    exact = [[20.123456789012, 100.98765432101], [140.0, 100.0], [130.0, 20.0], [30.0, 20.0]]
    make_project(tmp_path / "m", "ortho", ortho__gcp_px=exact)
    path = tmp_path / "m" / "project.toml"

    async def go():
        app = FieldToolApp(path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            assert _row(app, "ortho.gcp_px[0]").text() == "20.12, 100.99"
            assert "20.123456" not in _text(app)
            _row(app, "ortho.gcp_px[1]").control.value = "141, 100"
            await pilot.pause()

    run(go())
    got = load_project(path).ortho.gcp_px
    assert got[0] == exact[0] and got[1] == [141.0, 100.0]
    assert Field("section.station_offset_m", "x", "m", "point", "").format([1.23456, 2.0]) == "1.23456, 2"


def test_viewer_url_with_its_key_stays_on_screen_and_one_ssh_hint(tmp_path, monkeypatch):
    """Defect: the URL with its key was only in a toast; the ssh -L hint said USER@THIS-MACHINE in the TUI and
    root@localhost in the CLI. The title bar keeps the whole URL at 80 columns; the TUI's hint is the CLI's."""
    import fieldtool.viewer.server as server
    from fieldtool.viewer.guard import ssh_hint

    token = "AbCdEfGhIjKlMnOpQrStUvWx"

    class FakeViewer:
        port, url = 48765, f"http://127.0.0.1:48765/{token}/"
        in_process = True

        @property
        def ssh_hint(self):
            return ssh_hint(self.port)

        def stop(self):
            pass

    monkeypatch.setattr(server, "start_viewer", lambda *a, **k: FakeViewer())
    make_project(tmp_path / "m", "video")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+o")
            await pilot.pause(0.2)
            app.clear_notifications()
            await pilot.press("ctrl+n")  # another step, a later moment: the URL is still there
            await pilot.pause(0.5)
            lines = screen_lines(app)
            assert FakeViewer.url in lines[0], lines[0]
            assert "USER@THIS-MACHINE" not in app.status[0] and ssh_hint(48765) in app.status[0]
            assert "@localhost" not in ssh_hint(48765)

    run(go())


def test_progress_to_a_log_file_is_a_few_lines(monkeypatch):
    """Defect: a progress line written to a log file was one line of thousands of '\\r' updates."""
    import fieldtool.cli.console as console

    buf = io.StringIO()
    monkeypatch.setattr("sys.stderr", buf)
    for i in range(3000):
        console.progress_line(f"frames: {i}/3000")
    console.progress_line("PIV: pair 1/10")
    console.end_progress_line()
    out = buf.getvalue()
    assert "\r" not in out
    lines = out.splitlines()
    assert 2 <= len(lines) <= 6, lines
    assert lines[0].strip() == "frames: 0/3000" and any("PIV" in ln for ln in lines)


def test_a_value_typed_for_a_commented_out_key_replaces_that_line(tmp_path):
    """Defect: a value typed for a commented-out key was appended at the end of its table, the commented line
    kept."""
    from fieldtool.project.template import write_template

    path = write_template(tmp_path)
    p = load_project(path)
    p.step = "water_level"
    from fieldtool.project.sync import ProjectSync

    ProjectSync(path).save(p)

    async def go():
        app = FieldToolApp(path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            _row(app, "water_level.value_m").control.value = "12.5"
            await pilot.pause()

    run(go())
    text = path.read_text()
    assert not re.search(r"^#\s*value_m\s*=", text, re.M)
    table = text.split("[water_level]")[1].split("\n[")[0]
    assert table.count("value_m = 12.5") == 1
    lines = [ln for ln in table.splitlines() if ln.strip() and not ln.startswith("#")]
    assert lines[1].startswith("value_m = 12.5"), lines  # in its place, after method, not at the end


def _field_with_banks(ny=12, nx=30):
    """A field whose outer 8 columns each side are banks (valid, 0.002 px/s: texture that does not move) and
    the middle the water (4 px/s downstream)."""
    import numpy as np

    x, y = np.meshgrid(np.arange(nx) * 8.0, np.arange(ny) * 8.0)
    u = np.full((ny, nx), 0.002)
    v = np.zeros((ny, nx))
    u[:, 8 : nx - 8] = 4.0
    v[:, 8 : nx - 8] = 0.5
    return x, y, u, v


def test_piv_summary_is_measured_on_the_water_and_banks_draw_no_arrow(tmp_path):
    """Defect: the PIV step said "median speed 0.021 m/s" (every node, banks included), drew arrows on the
    banks, and the water rows could not be reached with page down."""
    import numpy as np

    from fieldtool.project.model import project_to_dict
    from fieldtool.tui.jobs import _preview
    from fieldtool.tui.piv_summary import water_nodes
    from fieldtool.tui.widgets.plots import VectorGrid

    x, y, u, v = _field_with_banks()
    water = water_nodes(u, v, np.ones_like(u))
    assert water[:, 8:22].all() and not water[:, :8].any() and not water[:, 22:].any()

    class Res:
        pass

    res = Res()
    res.x, res.y, res.u, res.v = x, y, u, v
    res.valid_fraction, res.n_pairs, res.u_pairs = np.ones_like(u), 9, []
    p = make_project(tmp_path / "m", "piv")
    preview = _preview(p, res, None)
    assert abs(preview["stats"]["median_speed_px_s"] - np.hypot(4.0, 0.5)) < 1e-9  # not 0.002 (the banks)

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            preview["inputs"] = project_to_dict(app.session.project)
            app.session.piv_preview = preview
            app.screen.refresh_view()
            await pilot.pause()
            for _ in range(4):
                await pilot.press("pagedown")
            await pilot.pause(0.3)
            text = _text(app)
            flat = " ".join(text.split())
            assert "168 of 360 nodes on the water" in flat and "median speed on the water 4.0 px/s" in flat, text
            grid = app.screen.query_one(VectorGrid)
            region = grid.region
            assert region.height > 0 and app.screen.region.contains_region(region)
            rows = screen_lines(app)[region.y : region.y + region.height]
            assert any("↘" in r or "→" in r for r in rows), rows  # the water's arrows are on screen

    run(go())
    # a bank node inside the water's rows and columns stays blank
    u2, v2 = u.copy(), v.copy()
    u2[5, 12] = 0.001
    g = VectorGrid()
    g.set_field(u2, v2, water_nodes(u2, v2))
    assert g.field[0].shape == (12, 14) and not g.water[5, 4]


def test_a_gcp_click_that_is_not_snapped_says_so(tmp_path):
    """Defect: a click 1.5-2.9 px from a GCP target (a small, far one: the far_bank demo's P2) was not snapped
    and the status did not say so. Snapped or not, the status says which."""
    import cv2
    import numpy as np

    from fieldtool.viewer.server import start_viewer

    (tmp_path / "frames").mkdir()
    img = np.full((120, 160, 3), 128, np.uint8)
    img[40:50, 60:70] = 0  # one checker target, 2 x 2 squares of 5 px, centre (69.5, 49.5)
    img[50:60, 70:80] = 0
    img[40:50, 70:80] = 255
    img[50:60, 60:70] = 255
    for i in range(2):
        cv2.imwrite(str(tmp_path / "frames" / f"f{i}.png"), img)
    path = tmp_path / "project.toml"
    path.write_text('[video]\npath = "frames/*.png"\nframe_interval_s = 0.1\n')
    h = start_viewer(path, port=0)
    try:
        h.set_mode("gcp")
        msg = h.click(20.0, 100.0)  # flat grey: no target near
        assert "P1 at" in msg and "NOT snapped" in msg and "NOT snapped" in h.status
        msg = h.click(71.5, 51.0)  # 2.5 px from the target's centre
        assert "snapped to the target centre" in msg, msg
    finally:
        h.stop()
