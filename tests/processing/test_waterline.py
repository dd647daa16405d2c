"""Automatic water line: edges found from the temporal activity along search lines, settled on the bank over
still water, several parallel lines checked against each other; the level, or a refusal that says why."""

import numpy as np
import pytest

from fieldtool.errors import GeometryError
from fieldtool.processing.cross_section import CrossSection
from fieldtool.processing.ortho import from_scale
from fieldtool.processing.water_level import waterline_level
from fieldtool.processing.waterline import extend_line, find_edges, settle_on_bank
from fieldtool.project.model import load_project
from fieldtool.run.geometry import level_and_mapping
from fieldtool.run.inputs import load_inputs


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


def _still_water_line(rng, n=400, left=80, still_to=110, right=320):
    """Profiles along a line: textured bank, still water (flat, water grey, no tracers) from the left edge to
    ``still_to``, active water to ``right``, bank."""
    x = np.arange(n)
    bank = (x < left) | (x >= right)
    mean = np.where(bank, 120 + 30 * np.sin(x / 3.0) + rng.normal(0, 10, n), 60 + rng.normal(0, 6, n))
    mean[left:still_to] = 45.0
    tex = np.where(bank, rng.uniform(8, 30, n), rng.uniform(1, 8, n))
    tex[left:still_to] = 0.2
    act = np.where(bank, rng.uniform(1.2, 2.0, n), rng.uniform(20, 50, n))
    act[left:still_to] = 0.5
    return mean, tex, act


def test_still_water_at_a_bank_is_walked_over_onto_the_bank():
    mean, tex, act = _still_water_line(np.random.default_rng(2))
    r = find_edges(act)
    assert r["edges"][0] == pytest.approx(110, abs=1.5)  # the activity alone stops at the still water
    s = settle_on_bank(mean, tex, act, r["threshold"], r["edges"])
    assert s["edges"][0] == pytest.approx(79.5, abs=1.0) and s["edges"][1] == pytest.approx(319.5, abs=1.0)
    assert s["still_water"][0] >= 25


def _lines(levels_width_m, scale=0.01, contrast=20.0):
    """``detected`` as detect_water_edges gives it, for lines whose edges are ``width / scale`` px apart."""
    out = []
    for k, w in enumerate(levels_width_m):
        x0 = 100.0
        out.append(
            {
                "offset_m": 0.4 * k,
                "line_px": np.array([[50.0, 100 + k], [1500.0, 100 + k]]),
                "edges_px": np.array([[x0, 100 + k], [x0 + w / scale, 100 + k]]),
                "sigma_px": np.array([1.5, 1.5]),
                "contrast": contrast,
                "still_water_px": [0.0, 0.0],
            }
        )
    return {"lines": out, "n_frames": 30}


V = CrossSection(np.array([0.0, 10.0, 20.0]), np.array([11.0, 10.0, 11.0]))  # V channel: width = 20 (z - 10)


def test_parallel_lines_that_agree_give_the_level():
    lv = waterline_level(V, from_scale(0.01), _lines([8.0, 8.02, 7.98, 8.01, 7.99]))
    assert lv.level_m == pytest.approx(10.4, abs=0.002)
    assert lv.details["lines_found"] == 5 and lv.details["doubtful"] == []


def test_parallel_lines_that_disagree_are_refused_naming_the_method_and_the_fix():
    with pytest.raises(
        GeometryError,
        match=r"water_level.method = waterline: could not find the water line reliably.*"
        r"type the level",
    ):
        waterline_level(V, from_scale(0.01), _lines([8.0, 10.0, 6.0, 8.0, 9.5]))  # levels 10.3..10.5: sd 8 cm


def test_a_level_too_uncertain_is_refused():
    det = _lines([8.0] * 5)
    for ln in det["lines"]:
        ln["sigma_px"] = np.array([400.0, 400.0])  # 4 m per edge on the water: a level +-14 cm
    with pytest.raises(GeometryError, match="uncertain by .* more than 5 cm"):
        waterline_level(V, from_scale(0.01), det)


def test_moderate_scatter_is_doubtful_and_widens_the_uncertainty():
    lv = waterline_level(V, from_scale(0.01), _lines([8.0, 8.6, 7.4, 8.0, 8.3]))  # sd ~2.4 cm of level
    assert [d["code"] for d in lv.details["doubtful"]] == ["waterline_scatter"]
    assert lv.uncertainty_m >= lv.details["lines_spread_m"]


def test_weak_contrast_between_water_and_banks_is_doubtful():
    lv = waterline_level(V, from_scale(0.01), _lines([8.0] * 5, contrast=4.0))  # wind-blown grass: Geul gives 3.6-4.8
    assert [d["code"] for d in lv.details["doubtful"]] == ["waterline_weak_contrast"]


def test_with_a_surveyed_station_each_edge_gives_a_level_and_they_must_agree():
    """Edges 8 m apart at px x = 100: on the V channel the level is 10.4 m with the edges at stations 6 and 14."""
    det = _lines([8.0, 8.0, 8.0])
    right = waterline_level(V, from_scale(0.01), det, station_of=lambda w: np.asarray(w)[:, 0] + 5.0)
    assert right.details["edge_levels"]["levels_m"] == pytest.approx([10.4, 10.4], abs=1e-6)
    assert right.details["doubtful"] == []
    # a station offset 2 m off puts the edges at 8 and 16 m: bank levels 10.2 and 10.6, doubtful
    off = waterline_level(V, from_scale(0.01), det, station_of=lambda w: np.asarray(w)[:, 0] + 7.0)
    assert off.level_m == pytest.approx(10.4, abs=1e-6)  # the width does not move
    assert [d["code"] for d in off.details["doubtful"]] == ["waterline_edges_disagree"]


def test_extend_line_is_clipped_to_the_frame():
    ln = extend_line([100, 100], [300, 200], 0.4, (240, 320))
    assert np.all(ln >= 0) and np.all(ln[:, 0] <= 319) and np.all(ln[:, 1] <= 239)
    d = np.diff(ln, axis=0)[0]
    assert d[1] / d[0] == pytest.approx(0.5)  # same direction


def _level_error(project_path, truth_level, **wl):
    p = load_project(project_path)
    p.water_level.method = "waterline"
    for k, v in wl.items():
        setattr(p.water_level, k, v)
    level, _ = level_and_mapping(p, load_inputs(p))
    return level.level_m - truth_level, level


def test_oblique_scene_level_within_2_cm(short_scene):
    err, level = _level_error(short_scene.project_path, short_scene.water_level_m)
    assert abs(err) < 0.02, f"{100 * err:+.2f} cm"
    assert 0 < level.uncertainty_m < 0.05
    assert level.method == "waterline" and level.details["lines_found"] >= 3 and level.details["contrast"] > 5


def test_a_search_line_on_the_water_only_is_refused(short_scene):
    """Drawn between the two water edges, the line never reaches a bank: the method must say it failed."""
    a, b = np.asarray(short_scene.section_px, float)
    inner = [list(a + 0.3 * (b - a)), list(a + 0.7 * (b - a))]
    with pytest.raises(GeometryError, match="water_level.method = waterline: could not find the water line reliably"):
        _level_error(short_scene.project_path, short_scene.water_level_m, search_line_px=inner)


@pytest.mark.slow
def test_nadir_scene_with_glints_level_within_2_cm(tmp_path):
    from fieldtool.synthetic import presets, render_scene

    truth = render_scene(
        presets.get("nadir", glints=True, duration_s=2.0), tmp_path / "s"
    )  # slow edge water needs ~2 s
    err, _ = _level_error(truth.project_path, truth.water_level_m)
    assert abs(err) < 0.02, f"{100 * err:+.2f} cm"
