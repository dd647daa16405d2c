"""Automatic water line: edges found from the temporal activity along a search line, then the level."""

import numpy as np
import pytest

from fieldtool.errors import GeometryError
from fieldtool.pipeline import level_and_mapping, load_inputs
from fieldtool.processing.waterline import extend_line, find_edges
from fieldtool.project import load_project


def _profile(rng, n=400, left=80.3, right=310.7, gaps=((150, 158), (240, 247))):
    x = np.arange(n)
    a = np.where((x > left) & (x < right), rng.uniform(20, 50, n), rng.uniform(1.2, 2.0, n))
    for g0, g1 in gaps:  # stretches of water where no tracer passed during the clip
        a[g0:g1] = 1.6
    return a


def test_edges_of_a_profile_with_gaps_in_the_tracers():
    r = find_edges(_profile(np.random.default_rng(0)))
    assert r["edges"][0] == pytest.approx(80.3, abs=1.0) and r["edges"][1] == pytest.approx(310.7, abs=1.0)
    assert r["contrast"] > 10


def test_refusals_say_why():
    rng = np.random.default_rng(1)
    with pytest.raises(GeometryError, match="could not find it"):
        find_edges(rng.uniform(1, 2, 300))
    with pytest.raises(GeometryError, match="does not reach the right bank"):
        find_edges(_profile(rng, right=1000))


def test_extend_line_is_clipped_to_the_frame():
    ln = extend_line([100, 100], [300, 200], 0.4, (240, 320))
    assert np.all(ln >= 0) and np.all(ln[:, 0] <= 319) and np.all(ln[:, 1] <= 239)
    d = np.diff(ln, axis=0)[0]
    assert d[1] / d[0] == pytest.approx(0.5)  # same direction


def _level_error(project_path, truth_level):
    p = load_project(project_path)
    p.water_level.method = "waterline"
    level, _ = level_and_mapping(p, load_inputs(p))
    return level.level_m - truth_level, level


def test_oblique_scene_level_within_2_cm(short_scene):
    err, level = _level_error(short_scene.project_path, short_scene.water_level_m)
    assert abs(err) < 0.02, f"{100 * err:+.2f} cm"
    assert 0 < level.uncertainty_m < 0.05
    assert level.method == "waterline" and level.details["contrast"] > 5


@pytest.mark.slow
def test_nadir_scene_with_glints_level_within_2_cm(tmp_path):
    from fieldtool.synthetic import presets, render_scene

    truth = render_scene(presets.get("nadir", glints=True, duration_s=2.0), tmp_path / "s")  # slow edge water needs ~2 s
    err, _ = _level_error(truth.project_path, truth.water_level_m)
    assert abs(err) < 0.02, f"{100 * err:+.2f} cm"
