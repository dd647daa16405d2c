"""The PIV field is reused only when everything it depends on is unchanged."""

import os

import pytest

from fieldtool.project.model import load_project
from fieldtool.run.observer import Observer
from fieldtool.run.pipeline import run_project


def test_reused_when_only_the_section_changes(scene):
    proj = load_project(scene / "project.toml")
    first = run_project(proj, scene / "out")
    assert not first.piv_reused and (scene / "out" / "piv_cache.npz").is_file()
    again = run_project(proj, scene / "out")
    assert again.piv_reused
    assert again.discharge.discharge_m3s == first.discharge.discharge_m3s
    assert list(again.q_pairs) == list(first.q_pairs)
    proj.section.n_sub = 7
    proj.section.alpha = 0.9
    proj.water_level.value_m -= 0.05
    changed = run_project(proj, scene / "out")
    assert changed.piv_reused and len(changed.discharge.area_m2) == 7
    assert changed.summary()["piv_reused"] is True


@pytest.mark.parametrize("change", ["window", "filters", "video_touched", "roi"])
def test_recomputed_when_an_input_of_piv_changes(scene, change):
    proj = load_project(scene / "project.toml")
    run_project(proj, scene / "out")
    if change == "window":
        proj.piv.window_px = 16
        proj.piv.overlap_px = 8
    elif change == "filters":
        proj.filters = [{"name": "clahe"}]
    elif change == "roi":
        proj.roi.rect_px = [v + 8 for v in proj.roi.rect_px]
    else:
        video = proj.resolve(proj.video.path)
        st = video.stat()
        os.utime(video, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert not run_project(proj, scene / "out").piv_reused


def test_damaged_cache_is_recomputed_and_observers_get_a_full_run(scene):
    proj = load_project(scene / "project.toml")
    run_project(proj, scene / "out")
    (scene / "out" / "piv_cache.npz").write_bytes(b"not a cache")
    assert not run_project(proj, scene / "out").piv_reused

    class Counting(Observer):
        pairs = 0

        def pair(self, *args):
            Counting.pairs += 1

    again = run_project(proj, scene / "out", observer=Counting())
    assert not again.piv_reused and Counting.pairs > 0
