"""The TUI at 80 x 24: what the operator must see is on screen (issue 14, "TUI at 80×24").

Each test names the defect it guards against. The project is the small fixed one of the snapshot
tests (a 160 x 120 px clip), so no PIV runs here; the PIV progress line is tested in test_tui_app.
"""

import asyncio
import re

import pytest
from test_tui_snapshots import SIZE, fake_result, make_project
from textual.widgets import DataTable, Input
from textual.widgets._toast import Toast

from fieldtool.tui.app import FieldToolApp
from fieldtool.tui.fields import Field, Invalid
from fieldtool.tui.screens.filters import parse_params
from fieldtool.tui.screens.preview import PreviewScreen
from fieldtool.tui.session import Session
from fieldtool.tui.steps import STEP_IDS
from fieldtool.tui.widgets.chrome import HelpLine, StatusLine
from fieldtool.tui.widgets.field_row import FieldRow
from fieldtool.tui.widgets.plots import GrayImage


def screen_lines(app) -> list[str]:
    """The text of every terminal line, as the operator sees it (modal screens and toasts included)."""
    return [strip.text for strip in app.screen._compositor.render_strips()]


def run(coro):
    return asyncio.run(coro)


def words(text: str) -> list[str]:
    return text.split()


@pytest.mark.parametrize("step", [s for s in STEP_IDS if s != "results"])
def test_help_wraps_never_cuts(step, tmp_path):
    """Defect: the help of the velocity index ("… else 0.") and of the ortho step were cut off.
    For every field of every step, the help line shows every word of the help, and no line of the
    80 x 24 screen ends inside a word of it (a word split over two lines would read as two)."""
    make_project(tmp_path / "m", step)

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            rows = [r for r in app.screen.query(FieldRow) if r.display]
            checked = 0
            for row in rows:
                row.control.focus()
                for _ in range(20):  # the help follows the focus on the next message round
                    await pilot.pause(0.02)
                    if row.field.key in str(app.screen.query_one(HelpLine).render()):
                        break
                help_w = app.screen.query_one(HelpLine)
                region = help_w.content_region
                assert region.bottom <= SIZE[1] - 2  # above the status line and the footer
                lines = screen_lines(app)[region.y : region.bottom]
                shown = [ln[region.x : region.right].strip() for ln in lines]
                expected = row.field.help_line(app.session.project)
                assert words(" ".join(shown))[-len(words(expected)) :] == words(expected), (row.field.key, shown)
                inp = row.control
                if isinstance(inp, Input) and not inp.value:  # the placeholder shows whole in the input
                    assert len(inp.placeholder) <= inp.content_region.width, (row.field.key, inp.placeholder)
                checked += 1
            assert checked == len(rows)

    run(go())


def test_velocity_index_help_is_whole(tmp_path):
    """The text the issue found cut ("… else 0."): the default of the velocity index, shown in its
    empty input (it was 33 characters in a 32-character input) and in the help line."""
    make_project(tmp_path / "m", "section")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            app.screen.query_one("#f-section-alpha Input").focus()
            await pilot.pause()
            text = " ".join(ln.strip() for ln in screen_lines(app))
            assert "Default: 0.8; 0.9 if mean depth >= 2 m." in text
            alpha_line = next(ln for ln in screen_lines(app) if "Velocity index" in ln)
            assert alpha_line.rstrip().endswith("0.8; 0.9 if mean depth >= 2 m")  # whole in its input

    run(go())


def test_toasts_do_not_cover_the_help_or_status_line(tmp_path):
    """Defect: toasts covered the help line."""
    make_project(tmp_path / "m", "video")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE, notifications=True) as pilot:
            await pilot.pause()
            app.notify("a long notification that takes a few lines of the screen " * 3, timeout=30)
            app.notify("a second one", timeout=30)
            await pilot.pause(0.3)
            toasts = list(app.screen.query(Toast))
            assert toasts
            bottom = min(app.screen.query_one(HelpLine).region.y, app.screen.query_one(StatusLine).region.y)
            for t in toasts:
                assert t.region.bottom <= bottom, (t.region, bottom)

    run(go())


def test_empty_ortho_fields_keep_every_distance_on_screen(tmp_path):
    """Defect: four 4-line "required" messages pushed L1-L6 off screen. Now a missing entry takes no
    line (red label, "✗ required" in the input) and a wrong one a single line."""
    make_project(tmp_path / "m", "ortho", ortho__gcp_px=[])

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            text = "\n".join(screen_lines(app))
            for i in range(1, 7):
                assert f"L{i} = |" in text, text
            assert text.count("✗ required") >= 4  # the four empty GCP inputs say it
            await pilot.press("ctrl+n")  # refused: the four messages, one line each, and L1-L6 in view
            await pilot.pause()
            assert app.screen.STEP == "ortho"
            text = "\n".join(screen_lines(app))
            assert text.count("✗ ortho.gcp_px[") == 4, text
            for i in range(1, 7):
                assert f"L{i} = |" in text, text
            # a wrong entry: one line under its field, the full message in the help line on focus
            app.screen.query_one("#f-ortho-distances_m-0 Input").focus()
            await pilot.press("-", "1")
            await pilot.pause()
            row = app.screen.query_one("#f-ortho-distances_m-0", FieldRow)
            box = row.query_one(".field-error")
            assert box.display and box.region.height == 1
            assert "must be greater than 0" in " ".join(screen_lines(app)[app.screen.query_one(HelpLine).region.y :])
            text = "\n".join(screen_lines(app))
            for i in range(1, 7):
                assert f"L{i} = |" in text, text

    run(go())


def test_typing_into_a_field_replaces_its_value(tmp_path):
    """Defect: typing into a field holding "0" appended to it ("010")."""
    make_project(tmp_path / "m", "video")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("tab")  # video.path -> video.start_s, which holds "0"
            await pilot.pause()
            inp = app.screen.query_one("#f-video-start_s Input", Input)
            assert app.focused is inp and inp.value == "0"
            await pilot.press("1", "0")
            await pilot.pause()
            assert inp.value == "10"

    run(go())


@pytest.mark.parametrize(
    "change, step, reason",
    [
        ({"video__start_s": 10.0, "video__end_s": None}, "video", "video.start_s"),  # 10 s past a 1 s clip
        ({"water_level__value_m": 0.1}, "water_level", "below the lowest bed point"),  # bed at 0.4 m
        ({"video__path": "bed.csv"}, "video", "cannot be read as a video"),  # a CSV given as the video
    ],
)
def test_sidebar_marks_wrong_entries(tmp_path, change, step, reason):
    """Defect: the sidebar showed ✓ on steps whose entries were wrong. Now ✗, with the reason in the
    sidebar (shortened) and in full in the help line when the step is highlighted."""
    make_project(tmp_path / "m", "cross_section", **change)
    s = Session(tmp_path / "m" / "project.toml")
    marks = s.step_marks()
    assert marks[step] == "invalid", (marks, s.mark_reasons)
    assert reason in s.mark_reasons[step]
    ok = make_project(tmp_path / "ok", "cross_section")
    good = Session(tmp_path / "ok" / "project.toml").step_marks()
    assert good[step] == "ok"

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            n = STEP_IDS.index(step) + 1
            sidebar = [ln[:24] for ln in screen_lines(app)]
            assert any(ln.startswith(f"✗{n:>2}") for ln in sidebar), sidebar
            steps = app.screen.query_one("#steps")
            steps.focus()
            steps.highlighted = STEP_IDS.index(step)
            await pilot.pause()
            help_text = " ".join(ln.strip() for ln in screen_lines(app)[app.screen.query_one(HelpLine).region.y :])
            assert reason.split()[0] in help_text

    run(go())
    assert ok is not None


def test_decimal_comma_is_read_or_answered():
    """Numbers typed with a decimal comma: one number is read ("2,5" = 2.5); where a comma also
    separates numbers, the message says to use a decimal point."""
    f = Field("water_level.value_m", "Water level", "m", "float", "level")
    assert f.parse("2,5") == 2.5
    assert f.parse("-0,25") == -0.25
    n = Field("section.n_sub", "Subsections", "", "int", "n")
    with pytest.raises(Invalid, match="decimal point"):
        n.parse("2,5")
    pair = Field("water_level.dem_x_m", "x", "m", "floats", "x", count=2)
    with pytest.raises(Invalid, match="decimal point"):
        pair.parse("1,5, 2,5")
    assert pair.parse("1.5, 2.5") == [1.5, 2.5]
    from fieldtool.errors import ParameterError

    with pytest.raises(ParameterError, match="decimal point"):
        parse_params("clip_limit=2,5", "clahe")


def test_discharge_table_says_how_to_scroll(tmp_path):
    """Defect: 11 of 15 subsections shown, the rest reachable by shift+tab then ↓ x14 with no hint.
    The table has the focus on arrival and a line says which rows are shown and how to scroll."""
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p, n=15)

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            table = app.screen.query_one(DataTable)
            assert app.focused is table
            text = "\n".join(screen_lines(app))
            m = re.search(r"subsections 1-(\d+) of 15 · ↑/↓ scroll", text)
            assert m, text
            for _ in range(14):
                await pilot.press("down")
            await pilot.pause(0.3)
            text = "\n".join(screen_lines(app))
            assert re.search(r"subsections \d+-15 of 15", text), text
            assert re.search(r"│\s+15\s", text), text  # the last row is on screen

    run(go())


def test_results_show_interval_grade_and_reasons(tmp_path):
    p = make_project(tmp_path / "m", "results")
    fake_result(tmp_path / "m", p, quality=True)

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause(0.3)
            text = " ".join(ln[24:].strip() for ln in screen_lines(app))
            assert "discharge      1.2345 m³/s  95 %: 1.069 .. 1.400" in text
            assert "doubtful: few valid vectors" in text

    run(go())


def test_filter_preview_is_large_and_written_for_the_viewer(tmp_path):
    """Defect: the filter preview was ~26 x 12 characters. ctrl+r now opens it at the size of the
    terminal and writes out/filter_preview.png, which the viewer shows as the "filtered" image."""
    make_project(tmp_path / "m", "filters")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+r")
            await pilot.pause(0.3)
            assert isinstance(app.screen, PreviewScreen)
            for img in app.screen.query(GrayImage):
                assert img.size.width >= 38 and img.size.height >= 15
            await pilot.press("escape")
            await pilot.pause()
            assert app.screen.STEP == "filters"

    run(go())
    png = tmp_path / "m" / "out" / "filter_preview.png"
    assert png.is_file()
    from fieldtool.project.model import load_project
    from fieldtool.viewer.images import load_display

    disp = load_display(load_project(tmp_path / "m" / "project.toml"), "filtered")
    assert disp.rgb.shape == (120, 160, 3)


def test_viewer_ssh_line_is_shown(tmp_path, monkeypatch):
    """The status line gives the exact port forward when the viewer opens."""
    import fieldtool.viewer.server as server

    class FakeViewer:
        port, url = 8765, "http://127.0.0.1:8765/"

        def stop(self):
            pass

    monkeypatch.setattr(server, "start_viewer", lambda *a, **k: FakeViewer())
    make_project(tmp_path / "m", "video")

    async def go():
        app = FieldToolApp(tmp_path / "m" / "project.toml")
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            await pilot.press("ctrl+o")
            await pilot.pause()
            text = "\n".join(screen_lines(app))
            assert "ssh -L 8765:127.0.0.1:8765" in text

    run(go())


def test_typing_in_the_tui_keeps_the_template_comments(tmp_path):
    """Defect: the `init` template's comments were all gone after the first save (the saving is
    helper valid's round-trip; this checks it from the TUI's keys)."""
    from fieldtool.project.template import write_template

    path = write_template(tmp_path / "m")
    before = path.read_text(encoding="utf-8")
    comments = [ln.split("#", 1)[1] for ln in before.splitlines() if "#" in ln]

    async def go():
        app = FieldToolApp(path)
        async with app.run_test(size=SIZE) as pilot:
            await pilot.pause()
            app.screen.query_one("#f-cross_section-path Input").focus()
            await pilot.press(*"bed.csv")
            await pilot.pause()

    run(go())
    after = path.read_text(encoding="utf-8")
    assert 'path = "bed.csv"' in after
    assert [ln.split("#", 1)[1] for ln in after.splitlines() if "#" in ln] == comments
