"""Inputs a hostile tester gives (issue 25): literal names with brackets, absurd or huge cross-sections, values
typed on the command line, a null discharge, a 2-frame clip, a JPEG cut short, an unwritable HOME."""

import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from fieldtool.cli.main import main
from fieldtool.errors import InputFileError
from fieldtool.processing import cross_section as xs
from fieldtool.processing import quality as ql
from fieldtool.processing.frames import FrameSource, sequence_files
from fieldtool.project.validation import path_problem


def _project(scene_dir: Path, edit=None, name="project.toml") -> Path:
    data = tomllib.loads((scene_dir / "project.toml").read_text())
    if edit:
        edit(data)
    p = scene_dir / name
    p.write_text(tomli_w.dumps(data))
    return p


def _images(folder: Path, n: int, ext=".png") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        p = folder / f"f{i:03d}{ext}"
        cv2.imwrite(str(p), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        out.append(p)
    return out


# --- literal names ----------------------------------------------------------------------------------


def test_a_folder_with_brackets_is_a_folder(tmp_path):
    folder = tmp_path / "site [A] 2024"
    _images(folder, 3)
    assert path_problem(folder, "video.path", kind="video") is None
    assert len(FrameSource(folder, frame_interval_s=0.1).files) == 3
    pattern = folder / "*.png"  # an explicit * in a folder with brackets: the brackets stay literal
    assert path_problem(pattern, "video.path", kind="video") is None
    assert len(FrameSource(pattern, frame_interval_s=0.1).files) == 3


def test_a_video_with_brackets_is_a_file(short_scene, tmp_path):
    video = tmp_path / "clip [1].mp4"
    shutil.copy(short_scene.project_path.parent / "river.mp4", video)
    (tmp_path / "clip 1.mp4").write_bytes(b"not this one")  # what the name would match as a pattern
    assert sequence_files(video) is None
    assert path_problem(video, "video.path", kind="video") is None
    assert FrameSource(video).info.n_frames > 2


def test_run_on_a_video_with_brackets(scene, capsys):
    shutil.move(scene / "river.mp4", scene / "clip [1].mp4")
    proj = _project(scene, lambda d: d["video"].update(path="clip [1].mp4"))
    code = main(["run", str(proj), "--out", str(scene / "out"), "--quiet"])
    assert code == 0, capsys.readouterr().err


def test_a_glob_is_a_glob_only_with_star_or_question_mark(tmp_path):
    folder = tmp_path / "frames"
    _images(folder, 4)
    assert len(sequence_files(folder / "f00?.png")) == 4
    assert len(sequence_files(folder / "f*.png")) == 4
    assert path_problem(folder / "f[0-9]*.png", "video.path", kind="video") is not None  # [0-9] is literal


# --- cross-sections -----------------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["1e308", "-1e308", "1e15", "12000"])
def test_absurd_elevation_is_refused_with_its_line(value):
    text = f"station,elevation\n0,10\n2,8\n4,{value}\n6,10\n"
    with pytest.raises(InputFileError, match=r"line 4: .*10 km"):
        xs.parse_xy_text(text, "cs.csv")


def test_absurd_station_is_refused_with_its_line():
    with pytest.raises(InputFileError, match=r"line 2: station .*10 km"):
        xs.parse_xy_text("0,10\n1e12,8\n2e12,10\n", "cs.csv")


def test_a_bank_a_thousand_times_higher_than_the_section_is_wide_is_refused():
    with pytest.raises(InputFileError, match=r"line 3: .*times"):
        xs.parse_xy_text("0,10\n1,8\n2,5000\n", "cs.csv")  # 4992 m of bank over 2 m of width
    xs.parse_xy_text("0,10\n1,8\n2,10\n", "cs.csv")  # an ordinary one still reads


def test_run_with_an_absurd_elevation_exits_2(scene, capsys):
    cs = (scene / "cross_section.csv").read_text().splitlines()
    i = next(k for k, ln in enumerate(cs) if ln[:1].isdigit() or ln[:1] == "-") + 3
    cs[i] = cs[i].split(",")[0] + ",1e308"
    (scene / "cross_section.csv").write_text("\n".join(cs) + "\n")
    code = main(["run", str(_project(scene)), "--out", str(scene / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and f"line {i + 1}" in err, err
    assert not (scene / "out").exists()


def test_a_50_mb_cross_section_answers_in_seconds(scene):
    rows = "".join(f"{i * 0.001:.3f},{10 - (i % 7) * 0.1:.2f}\n" for i in range(200_000))
    with open(scene / "cross_section.csv", "w") as fh:
        fh.write("station,elevation\n")
        while fh.tell() < 50_000_000:
            fh.write(rows)
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "fieldtool.cli", "run", str(_project(scene)), "--out", str(scene / "out"), "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    assert "cross_section.csv" in r.stderr and "MB" in r.stderr and len(r.stderr.splitlines()) == 1
    assert time.monotonic() - t0 < 60


# --- values typed on the command line go through the validation layer -----------------------------------


@pytest.mark.parametrize(
    "option", [["--level", "nan"], ["--level", "inf"], ["--level", "9.5", "--level-uncertainty", "-0.1"]]
)
def test_new_measurement_refuses_values_the_project_refuses(tmp_path, capsys, option):
    from test_sites import make_project

    src = make_project(tmp_path / "p")
    root = tmp_path / "sites"
    assert main(["site", "create", "st7", "--from", str(src), "--sites", str(root)]) == 0
    v = tmp_path / "new.mp4"
    v.write_bytes(b"v")
    capsys.readouterr()
    code = main(
        [
            "site",
            "new-measurement",
            "st7",
            "--sites",
            str(root),
            "--video",
            str(v),
            *option,
            "--out",
            str(tmp_path / "visit"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "water_level." in err, err
    assert not (tmp_path / "visit" / "project.toml").exists()


# --- verdicts -----------------------------------------------------------------------------------------


def _evidence(**kw):
    base = dict(
        subsection_width_m=np.ones(5),
        subsection_velocity_ms=np.full(5, 0.8),
        discharge_m3s=4.0,
        valid_fraction_section=0.9,
        peak_median=0.6,
        n_frame_pairs=100,
    )
    base.update(kw)
    return ql.Evidence(**base)


@pytest.mark.parametrize("q", [float("nan"), float("inf"), None])
def test_a_null_discharge_is_unusable(q):
    v = ql.assess(_evidence(discharge_m3s=q))
    assert v.grade == "unusable" and v.reasons[0].code == "no_discharge"


def test_a_single_pair_is_not_good():
    assert ql.assess(_evidence()).grade == "good"
    v = ql.assess(_evidence(n_frame_pairs=1))
    assert v.grade != "good" and any(r.code == "few_pairs" for r in v.reasons)


def test_cli_never_exits_0_on_a_null_discharge(scene, capsys, monkeypatch):
    """Whatever the quality checks say (here: they failed), no discharge means exit 3."""
    from fieldtool.run import assess

    def broken(*a, **k):
        raise RuntimeError("no verdict")

    monkeypatch.setattr(assess, "assess_run", broken)
    from fieldtool.processing import discharge as dq

    real = dq.compute_discharge

    def nan_q(*a, **k):
        r = real(*a, **k)
        r.discharge_m3s = float("nan")
        return r

    monkeypatch.setattr(dq, "compute_discharge", nan_q)
    code = main(["run", str(_project(scene)), "--out", str(scene / "out"), "--quiet"])
    out = capsys.readouterr()
    assert code == 3, out.err
    assert "unusable" in out.err


def test_two_frame_clip_is_not_graded_good(scene, capsys):
    import json

    cap = cv2.VideoCapture(str(scene / "river.mp4"))
    frames = scene / "two"
    frames.mkdir()
    for i in range(2):
        ok, img = cap.read()
        cv2.imwrite(str(frames / f"f{i}.png"), img)
    cap.release()
    proj = _project(scene, lambda d: d["video"].update(path="two", frame_interval_s=1 / 30))
    code = main(["run", str(proj), "--out", str(scene / "out"), "--quiet"])
    capsys.readouterr()
    assert code in (0, 3)
    grade = json.loads((scene / "out" / "result.json").read_text())["quality"]["grade"]
    assert grade != "good"


# --- damaged images, an unwritable HOME ---------------------------------------------------------------------


def test_a_jpeg_cut_short_is_refused_without_libjpeg_lines(tmp_path):
    files = _images(tmp_path / "seq", 6, ".jpg")
    data = files[3].read_bytes()
    files[3].write_bytes(data[: len(data) // 2])
    code = (
        "import sys\n"
        "from fieldtool.processing.frames import FrameSource\n"
        "from fieldtool.errors import FieldToolError\n"
        f"try:\n    src = FrameSource({str(tmp_path / 'seq')!r}, frame_interval_s=0.1)\n"
        "    [f for f in src]\nexcept FieldToolError as e:\n    print(e, file=sys.stderr); sys.exit(2)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "f003.jpg" in lines[0] and "cut short" in lines[0], r.stderr


def test_unwritable_home_adds_no_matplotlib_lines(scene, tmp_path_factory):
    blocker = tmp_path_factory.mktemp("home") / "a_file"
    blocker.write_text("")  # HOME below a file: nothing can be made there, not even by root
    env = {k: v for k, v in os.environ.items() if k not in ("MPLCONFIGDIR", "XDG_CONFIG_HOME", "XDG_CACHE_HOME")}
    env["HOME"] = str(blocker / "home")
    env["FIELDTOOL_DB"] = str(blocker / "home" / "history.sqlite")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "fieldtool.cli",
            "run",
            str(_project(scene)),
            "--out",
            str(scene / "out"),
            "--quiet",
            "--record",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert "matplotlib" not in r.stderr.lower(), r.stderr
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.parametrize(
    "key,value",
    [
        ("water_level.value_m", float("nan")),
        ("water_level.uncertainty_m", -0.1),
        ("ortho.gcp_px", [[1.0, 2.0], [float("inf"), 3.0]]),
    ],
)
def test_a_single_key_written_from_outside_goes_through_validation(short_scene, tmp_path, key, value):
    """calibrate --project and the viewer write one key (project.sync.ProjectSync.set_keys): refused like the rest."""
    from fieldtool.errors import ParameterError
    from fieldtool.project.sync import ProjectSync

    proj = tmp_path / "project.toml"
    shutil.copy(short_scene.project_path, proj)
    before = proj.read_bytes()
    with pytest.raises(ParameterError, match=key.replace(".", r"\.")):
        ProjectSync(proj).set_keys({key: value})
    assert proj.read_bytes() == before
