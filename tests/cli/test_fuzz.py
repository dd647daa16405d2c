"""A bounded sample of the fuzz table (tests/fuzz_cases.py); the full set is benchmarks/fuzz_all.py.

Every case: exit 2 with one line where the value cannot be right (0/2/3 otherwise), no traceback,
the project file's bytes unchanged, the output folder still holding one complete run, strict JSON.
"""

import shutil

import fuzz_cases as F
import pytest


@pytest.fixture(scope="module")
def runner(short_scene, tmp_path_factory):
    from fieldtool.cli.main import main

    work = tmp_path_factory.mktemp("fuzz")
    scene = work / "scene"
    scene.mkdir()
    for p in (short_scene.project_path, short_scene.video_path, short_scene.cross_section_path):
        shutil.copy(p, scene / p.name)
    seed = work / "seed_out"
    assert main(["run", str(scene / "project.toml"), "--out", str(seed), "--quiet"]) == 0
    return F.Runner(scene, seed, work / "cases")


def _sample():
    keys = [c for c in F.key_cases(full=False) if c.must_refuse][::16]
    passing = [c for c in F.key_cases(full=False) if c.id in ("name=unicode", "video.start_s=zero")]
    files = [c for c in F.file_cases() if c.id in ("project-binary", "project-truncated", "video-fifo", "xs-binary")]
    cmds = [
        c
        for c in F.command_cases()
        if c.id in ("calibrate-square-inf", "report-list-json", "batch-levels-no-delimiter", "run-out-is-file")
    ]
    return keys + passing + files + cmds


SAMPLE = _sample()


@pytest.mark.parametrize("case", SAMPLE, ids=[c.id for c in SAMPLE])
def test_fuzz_case(runner, case, short_scene):
    o = runner.run(case)
    assert o.ok, (
        case.id,
        o.rc,
        o.stderr[-600:],
        {
            k: getattr(o, k)
            for k in ("traceback", "multi_line", "damaged_project", "partial_output", "non_json", "wrong_code", "hang")
        },
    )


def test_geometry_cases(runner, short_scene):
    from fieldtool.project.model import load_project

    gcp = load_project(short_scene.project_path).ortho.gcp_px
    bad = [(c.id, o.rc, o.stderr[-300:]) for c in F.geometry_cases(gcp) for o in [runner.run(c)] if not o.ok]
    assert not bad, bad
