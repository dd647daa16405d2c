"""The CLI: bad input gets one clear message naming the file or key, exit code 2, no traceback."""

import json
import shutil
import subprocess
import sys
import tomllib

import pytest
import tomli_w

from fieldtool.cli.main import main


def _copy_project(scene, tmp_path, edit=None):
    src = scene.project_path.parent
    for f in src.iterdir():
        if f.is_file():
            shutil.copy(f, tmp_path / f.name)
    data = tomllib.loads((tmp_path / "project.toml").read_text())
    if edit:
        edit(data)
    (tmp_path / "project.toml").write_text(tomli_w.dumps(data))
    return tmp_path / "project.toml"


def _run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_run_succeeds_and_writes_outputs(short_scene, tmp_path, capsys):
    proj = _copy_project(short_scene, tmp_path)
    code, out, _ = _run(capsys, "run", str(proj), "--out", str(tmp_path / "out"), "--quiet")
    assert code == 0, out
    assert "discharge" in out
    for name in (
        "result.json",
        "subsections.csv",
        "mean_field.npz",
        "mean_field.npy",
        "vectors.png",
        "rectified.png",
        "section.png",
    ):
        assert (tmp_path / "out" / name).is_file(), name


def _set(path, value):
    def edit(d):
        node = d
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = value

    return edit


CASES = [
    ("missing video", _set(("video", "path"), "nope.mp4"), "nope.mp4: video not found"),
    ("unreadable video", _set(("video", "path"), "junk.mp4"), "junk.mp4: cannot be read as a video"),
    ("one-point section", None, "at least 2 rows"),
    ("non-increasing stations", None, "station must increase"),
    ("level below the bed", _set(("water_level", "value_m"), -50.0), "below the lowest bed point"),
    ("level above the banks", _set(("water_level", "value_m"), 500.0), "above both banks"),
    ("triangle inequality", _set(("ortho", "distances_m"), [5.0, 5.0, 5.0, 5.0, 50.0, 5.0]), "cannot form a triangle"),
    ("start after the end", _set(("video", "start_s"), 100.0), "video.start_s: 100 s is outside the clip"),
    ("window larger than the image", _set(("piv", "window_px"), 4096), "piv.window_px"),
    ("section point outside", _set(("section", "points_px"), [[10.0, 10.0], [5000.0, 10.0]]), "section.points_px[1]"),
    ("unknown key", _set(("piv", "windoww"), 3), "unknown key piv.windoww"),
]


@pytest.mark.parametrize("name,edit,message", CASES, ids=[c[0] for c in CASES])
def test_bad_input_exit_2(short_scene, tmp_path, capsys, name, edit, message):
    proj = _copy_project(short_scene, tmp_path, edit)
    (tmp_path / "junk.mp4").write_bytes(b"\x00not a video" * 200)
    if name == "one-point section":
        (tmp_path / short_scene.cross_section_path.name).write_text("station,elevation\n0,1\n")
    if name == "non-increasing stations":
        (tmp_path / short_scene.cross_section_path.name).write_text("0,1\n2,0\n1,1\n")
    code, out, err = _run(capsys, "run", str(proj), "--out", str(tmp_path / "out"), "--quiet")
    assert code == 2
    assert message in err, err
    assert "Traceback" not in err


def test_missing_project_via_subprocess(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "fieldtool.cli.main", "run", str(tmp_path / "none.toml")], capture_output=True, text=True
    )
    assert res.returncode == 2 and "project file not found" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("case", ["good", "rerun", "bad"])
def test_run_as_the_program_leaves_at_once_after_its_exit_handlers(short_scene, tmp_path, case):
    """`fieldtool run` ends with os._exit after the exit handlers (cli.main._leave): the handlers still run, its
    output is all there and flushed (a rerun recording complete), the exit code is the command's; called as a
    function, main returns."""
    good = case != "bad"
    flag = tmp_path / "handler-ran"
    project = short_scene.project_path if good else tmp_path / "none.toml"
    extra = ["--rerun", "save"] if case == "rerun" else []
    code = (
        "import atexit, sys; from fieldtool.cli import main; "
        f"atexit.register(lambda: open({str(flag)!r}, 'w').write('ran')); "
        f"sys.argv = ['fieldtool', 'run', {str(project)!r}, '--out', {str(tmp_path / 'out')!r}, *{extra!r}]; "
        "main.main(); print('not reached')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert flag.read_text() == "ran"
    assert "not reached" not in r.stdout
    if good:
        assert r.returncode == 0, r.stderr
        assert any(line.startswith("quality") for line in r.stdout.splitlines()), r.stdout  # late lines, flushed
        assert json.loads((tmp_path / "out" / "result.json").read_text())["discharge_m3s"] > 0
        if case == "rerun":  # the recording's last entity, logged at the run's end, is in the file
            from rerun.chunk import RrdReader

            paths = {ch.entity_path for ch in RrdReader(tmp_path / "out" / "run.rrd").stream()}
            assert "/discharge/final_m3s" in paths, sorted(paths)
    else:
        assert r.returncode == 2 and "project file not found" in r.stderr


def test_init_refuses_to_overwrite(tmp_path, capsys):
    assert _run(capsys, "init", str(tmp_path))[0] == 0
    code, _, err = _run(capsys, "init", str(tmp_path))
    assert code == 2 and "already exists" in err


def test_section_picked_right_to_left_is_swapped(short_scene):
    from fieldtool.project.model import load_project
    from fieldtool.run.pipeline import run_project

    proj = load_project(short_scene.project_path)
    ref = run_project(proj, None)
    proj.section.points_px = proj.section.points_px[::-1]
    swapped = run_project(proj, None)
    assert swapped.section.swapped and any("swapped" in w for w in swapped.warnings)
    assert swapped.discharge.discharge_m3s == pytest.approx(ref.discharge.discharge_m3s, rel=1e-9)


def test_the_parser_leaves_scipy_and_the_pipeline_out():
    """Every `fieldtool ...` builds the parser: SciPy, the run's pipeline and the station's records (0.6-0.8 s of
    imports together) load only for the command that needs them."""
    heavy = ("scipy", "matplotlib", "fieldtool.run.pipeline", "fieldtool.records.station", "textual", "viser")
    code = (
        "import sys; from fieldtool.cli.main import build_parser; build_parser(); "
        f"print([m for m in {heavy!r} if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


def test_a_run_imports_neither_scipy_optimize_nor_scipy_spatial_at_its_start():
    """`fieldtool run` imports the pipeline before its first frame: scipy.optimize (a lens fit, the angle-and-height
    level) and scipy.spatial (the NetCDF grid, written at the end) cost 0.3 s there and load only when used."""
    heavy = ("scipy.optimize", "scipy.spatial", "scipy.interpolate")
    code = (
        "import sys; import fieldtool.cli.measure, fieldtool.run.pipeline, fieldtool.run.outputs; "
        f"print([m for m in {heavy!r} if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr
