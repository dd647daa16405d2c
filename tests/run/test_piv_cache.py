"""The PIV field is reused only when everything it depends on is unchanged."""

import os
import shutil

import pytest

from fieldtool.project.model import load_project
from fieldtool.run.observer import Observer
from fieldtool.run.pipeline import run_project


@pytest.fixture(scope="module")
def first_run(short_scene, tmp_path_factory):
    """The short scene's files and one run of it into ``out`` (its PIV cache written), made once for the module:
    (folder, result). Tests start from a copy (``primed``), never from this folder."""
    src = tmp_path_factory.mktemp("piv_cache_first")
    for f in short_scene.project_path.parent.iterdir():
        if f.is_file():
            shutil.copy2(f, src / f.name)
    return src, run_project(load_project(src / "project.toml"), src / "out")


@pytest.fixture
def primed(first_run, tmp_path):
    """This test's own copy of the scene after its first run: the files with their modification times (the cache
    key holds them) and the output folder with its ``piv_cache.npz``."""
    src, _ = first_run
    for f in src.iterdir():
        if f.is_file():
            shutil.copy2(f, tmp_path / f.name)
    shutil.copytree(src / "out", tmp_path / "out")
    return tmp_path


def test_reused_when_only_the_section_changes(first_run, primed):
    _, first = first_run
    assert not first.piv_reused and (primed / "out" / "piv_cache.npz").is_file()
    proj = load_project(primed / "project.toml")
    again = run_project(proj, primed / "out")
    assert again.piv_reused
    assert again.discharge.discharge_m3s == first.discharge.discharge_m3s
    assert list(again.q_pairs) == list(first.q_pairs)
    proj.section.n_sub = 7
    proj.section.alpha = 0.9
    proj.water_level.value_m -= 0.05
    changed = run_project(proj, primed / "out")
    assert changed.piv_reused and len(changed.discharge.area_m2) == 7
    assert changed.summary()["piv_reused"] is True


@pytest.mark.parametrize("change", ["window", "filters", "video_touched", "roi"])
def test_recomputed_when_an_input_of_piv_changes(primed, change):
    proj = load_project(primed / "project.toml")
    if change == "window":
        proj.piv.window_px = 16
        proj.piv.overlap_px = 8
    elif change == "filters":
        proj.filters = [{"name": "clahe"}]
    elif change == "roi":
        proj.roi.rect_px = [v + 8 for v in proj.roi.rect_px]
    elif change == "video_touched":
        video = proj.resolve(proj.video.path)
        st = video.stat()
        os.utime(video, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert not run_project(proj, primed / "out").piv_reused  # unchanged, the copy is reused (test above)


def test_damaged_cache_is_recomputed_and_observers_get_a_full_run(primed):
    proj = load_project(primed / "project.toml")
    (primed / "out" / "piv_cache.npz").write_bytes(b"not a cache")
    assert not run_project(proj, primed / "out").piv_reused

    class Counting(Observer):
        pairs = 0

        def pair(self, *args):
            Counting.pairs += 1

    again = run_project(proj, primed / "out", observer=Counting())
    assert not again.piv_reused and Counting.pairs > 0
