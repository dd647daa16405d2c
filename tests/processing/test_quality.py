"""Plausibility of the inputs, the quality verdict and the Monte Carlo interval of Q (issue 11)."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from fieldtool.cli.main import main as cli_main
from fieldtool.errors import GeometryError
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho
from fieldtool.processing import quality as ql
from fieldtool.processing import uncertainty as un
from fieldtool.processing.cross_section import CrossSection
from fieldtool.project.model import load_project, save_project


def _variant(scene, name: str, change) -> Path:
    """A copy of the scene's project with ``change(project)`` applied, saved beside it."""
    p = load_project(scene.project_path)
    change(p)
    path = scene.project_path.parent / f"project_{name}.toml"
    save_project(p, path)
    return path


def _run(path: Path, out: Path, capsys) -> tuple[int, str]:
    code = cli_main(["run", str(path), "--out", str(out), "--quiet"])
    cap = capsys.readouterr()
    return code, cap.out + cap.err


# --------------------------------------------------------------------------------------------- input mistakes


def test_p3_p4_swapped_is_refused_naming_the_points(short_scene, tmp_path, capsys):
    def swap(p):
        p.ortho.gcp_px[2], p.ortho.gcp_px[3] = p.ortho.gcp_px[3], p.ortho.gcp_px[2]

    code, text = _run(_variant(short_scene, "p3p4", swap), tmp_path / "out", capsys)
    assert code == 2
    assert "P3 and P4 look swapped" in text and "Traceback" not in text


def test_double_click_section_is_refused_with_its_length(short_scene, tmp_path, capsys):
    def dbl(p):
        x, y = p.section.points_px[0]
        p.section.points_px = [[x, y], [x + 2.0, y]]

    code, text = _run(_variant(short_scene, "dbl", dbl), tmp_path / "out", capsys)
    assert code == 2
    assert "section.points_px" in text and "12.00 m wide" in text and "min_length_fraction" in text


def test_l5_typo_names_l5_and_accepting_it_makes_the_run_doubtful(short_scene, tmp_path, capsys):
    def typo(p):
        p.ortho.distances_m[4] = 17.7785

    code, text = _run(_variant(short_scene, "l5", typo), tmp_path / "out", capsys)
    assert code == 2
    assert "the suspect is L5=|P1P3|" in text and "ortho.accept_residual" in text

    def typo_accepted(p):
        typo(p)
        p.ortho.accept_residual = True

    code, text = _run(_variant(short_scene, "l5ok", typo_accepted), tmp_path / "out", capsys)
    assert code in (0, 3)
    res = json.loads((tmp_path / "out" / "result.json").read_text())
    codes = [r["code"] for r in res["quality"]["reasons"]]
    assert "gcp_residual" in codes and res["quality"]["grade"] != "good"


@pytest.mark.parametrize("k", range(6))
def test_a_two_metre_typo_in_any_distance_is_named(short_scene, k):
    d = list(load_project(short_scene.project_path).ortho.distances_m)
    d[k] += 2.0
    with pytest.raises(GeometryError, match=rf"the suspect is L{k + 1}="):
        ortho.from_distances(short_scene.gcp_px, d, max_residual_m=0.1, frame_shape=(720, 1280))


def test_distances_in_millimetres_are_refused():
    px = np.array([[100, 600], [900, 600], [800, 200], [200, 200]], float)
    with pytest.raises(GeometryError, match="millimetres"):
        ortho.from_distances(px, [8000, 13600, 8000, 13600, 15778, 15778])


def test_a_point_inside_the_others_triangle_is_named():
    px = np.array([[100, 600], [900, 600], [500, 500], [200, 200]], float)
    with pytest.raises(GeometryError, match="P3 .* inside the triangle"):
        ortho.check_gcp_order(px)


def test_world_method_names_the_worst_gcp(short_scene):
    world = np.asarray(short_scene.gcp_world_m)[:, :2].copy()
    px = np.asarray(short_scene.gcp_px, float)
    px5 = np.r_[px, [px.mean(axis=0)]]
    w5 = np.r_[world, [world.mean(axis=0) + [0.0, 1.5]]]  # the fifth GCP's coordinates are 1.5 m off
    m = ortho.from_world_points(px5, w5)
    with pytest.raises(GeometryError, match="GCP 5 misses"):
        ortho.check_gcp_residuals(m, px5, 0.1)
    ortho.check_gcp_residuals(m, px5, 0.1, accept_residual=True)
    assert m.details["residual_accepted"] and len(m.details["gcp_reprojection_px"]) == 5


def _rect_cs() -> CrossSection:
    return CrossSection(np.array([0.0, 1.0, 11.0, 12.0]), np.array([2.0, 0.0, 0.0, 2.0]))


def test_section_ends_off_the_water_edges_are_refused():
    cs = _rect_cs()  # water edges at stations 0.5 and 11.5 at level 1.0: 11 m wide
    m = ortho.from_scale(0.01)  # 1 cm per pixel, nadir
    ok = dq.section_geometry([[50, 0], [1150, 0]], m, cs, 1.0, 10)
    dq.check_section(ok, cs, 1.0)
    short = dq.section_geometry([[50, 0], [700, 0]], m, cs, 1.0, 10)
    with pytest.raises(GeometryError, match="stops short of the water edges by 4.50 m"):
        dq.check_section(short, cs, 1.0)
    over = dq.section_geometry([[0, 0], [1450, 0]], m, cs, 1.0, 10)
    with pytest.raises(GeometryError, match="over a bank"):
        dq.check_section(over, cs, 1.0)
    off = dq.section_geometry([[0, 0], [1100, 0]], m, cs, 1.0, 10, station_offset_m=3.0)
    with pytest.raises(GeometryError, match="P1 at station 3.00 m, water edge at 0.50 m"):
        dq.check_section(off, cs, 1.0)


# --------------------------------------------------------------------------------------------- the verdict


def _ev(v, **kw) -> ql.Evidence:
    v = np.asarray(v, float)
    return ql.Evidence(subsection_width_m=np.ones(len(v)), subsection_velocity_ms=v, discharge_m3s=10.0, **kw)


def test_good_when_nothing_is_wrong():
    q = ql.assess(
        _ev(
            np.full(10, 1.0),
            valid_fraction_section=0.9,
            displacement_px=5,
            median_displacement_px=4,
            first_window_px=64,
            peak_median=0.5,
            flow_angle_deg=5,
            max_speed_ms=1.2,
        )
    )
    assert q.grade == "good" and q.reasons == []


def test_stalled_subsections_make_it_doubtful_then_unusable():
    v = np.full(10, 1.0)
    v[4] = -0.05
    q = ql.assess(_ev(v))
    assert (
        q.grade == "doubtful" and q.reasons[0].code == "stalled_subsections" and "5 (-0.05 m/s)" in q.reasons[0].message
    )
    v[2:6] = 0.02
    assert ql.assess(_ev(v)).grade == "unusable"


def test_filled_width_and_displacement_reasons_carry_numbers_and_the_setting():
    v = np.full(10, 1.0)
    v[:3] = np.nan
    q = ql.assess(_ev(v, displacement_px=20.0, first_window_px=64))
    codes = {r.code: r for r in q.reasons}
    assert codes["measured_width"].value == pytest.approx(0.7) and codes["measured_width"].threshold == 0.8
    assert "piv.search_px" in codes["displacement_limit"].message
    assert q.grade == "doubtful"
    assert ql.assess(_ev(v, displacement_px=40.0, first_window_px=64)).grade == "unusable"


def test_with_a_first_guess_the_displacement_check_reads_the_residual():
    """22 px per frame in a 64 px window is beyond the one-quarter rule, but not when the first pass moved its
    windows by the first look's field and only 2 px were left to find; 20 px left is doubtful again."""
    v = np.full(10, 1.0)
    assert "displacement_limit" not in {
        r.code for r in ql.assess(_ev(v, displacement_px=22.0, residual_px=2.0, first_window_px=64)).reasons
    }
    q = ql.assess(_ev(v, displacement_px=22.0, residual_px=20.0, first_window_px=64))
    r = {r.code: r for r in q.reasons}["displacement_limit"]
    assert "first look" in r.message and r.value == pytest.approx(20 / 64) and q.grade == "doubtful"


def test_speed_bound_and_no_motion_are_unusable():
    q = ql.assess(_ev(np.full(5, 20.0), max_speed_ms=21.0))
    assert q.grade == "unusable" and q.reasons[0].code == "speed_bound"
    q = ql.assess(_ev(np.full(5, 0.001), median_displacement_px=0.0, identical_frames=1.0, n_frame_pairs=30))
    assert q.grade == "unusable" and {"no_motion", "identical_frames"} <= {r.code for r in q.reasons}


def test_a_new_check_is_one_function():
    def disagree(ev, th):
        return (
            [ql.Reason("stiv_disagrees", "doubtful", "STIV says otherwise", 0.2, 0.1)] if ev.extra.get("stiv") else []
        )

    q = ql.assess(_ev(np.ones(5), extra={"stiv": True}), checks=[*ql.CHECKS, disagree])
    assert q.grade == "doubtful" and q.to_dict()["reasons"][0]["code"] == "stiv_disagrees"


def test_quality_keys_match_the_thresholds():
    from fieldtool.project.model import Project
    from fieldtool.run.assess import thresholds

    assert thresholds(Project()) == ql.Thresholds()


# --------------------------------------------------------------------------------------------- Monte Carlo


def _model(n_pairs: int = 12) -> un.McModel:
    """A nadir view at 1 cm/px over an 11 m wide flat-bed channel, uniform 1 m/s with pair noise."""
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.arange(0, 1200, 16.0), np.arange(-200, 200, 16.0))
    u = np.zeros_like(x)
    v = np.full_like(x, -100.0)  # -y in the image = +Y in the world: the downstream normal of P1 -> P2 (along +X)
    return un.McModel(
        cross_section=_rect_cs(),
        level_m=1.0,
        section_px=np.array([[50.0, 0.0], [1150.0, 0.0]]),
        n_sub=10,
        station_offset_m=None,
        alpha=0.85,
        mapping_fn=lambda g, r, lv: np.diag([0.01, -0.01, 1.0]),
        method="none",
        gcp_px=np.zeros((0, 2)),
        gcp_ref=np.zeros(0),
        x=x,
        y=y,
        u=u,
        v=v,
        u_pairs=u + rng.normal(0, 10, (n_pairs,) + x.shape),
        v_pairs=v + rng.normal(0, 10, (n_pairs,) + x.shape),
    )


def test_monte_carlo_budget_shares_sum_to_one_and_level_sigma_widens_it():
    m = _model()
    q0 = 0.85 * 1.0 * 10.5  # alpha * v * wetted area (1 m deep, 10 m flat bed, 0.5 m banks each side)
    narrow = un.monte_carlo_discharge(m, un.McSigmas(level_m=0.01), q0, n_draws=300, n_draws_source=80)
    wide = un.monte_carlo_discharge(m, un.McSigmas(level_m=0.1), q0, n_draws=300, n_draws_source=80)
    for r in (narrow, wide):
        assert sum(b["share"] for b in r.budget) == pytest.approx(1.0)
        assert [b["source"] for b in r.budget] == list(un.SOURCES)
        assert r.ci95_m3s[0] <= q0 <= r.ci95_m3s[1]
    assert wide.relative_u95 > 1.5 * narrow.relative_u95
    share = {b["source"]: b["share"] for b in wide.budget}
    assert share["water_level"] == max(share.values())
    d = wide.to_dict()
    assert d["method"] == "monte_carlo" and d["n_draws"] == 300 and json.dumps(d)


def test_monte_carlo_interval_follows_a_discharge_of_other_velocities():
    """velocity_source auto/stiv/combined: the draws perturb the PIV field, whose own discharge is q0; the run
    reports 3 % more (the combined velocities). The interval is PIV's draws scaled so that their median is the
    reported Q: PIV's relative width around it, instead of being stretched from PIV's interval to reach it. A field
    whose draws do not centre on its own discharge (PIV pairs that scatter under wind ripples: 14 % below) gets the
    same interval: the ratio of the two discharges would have left Q at the interval's edge."""
    m = _model()
    q0 = 0.85 * 1.0 * 10.5
    sig = un.McSigmas(level_m=0.05)
    piv = un.monte_carlo_discharge(m, sig, q0, n_draws=300, n_draws_source=80)
    other = un.monte_carlo_discharge(m, sig, 1.03 * q0, n_draws=300, n_draws_source=80, field_discharge_m3s=q0)
    k = [o / p for o, p in zip(other.ci95_m3s, piv.ci95_m3s, strict=True)]
    assert k[0] == pytest.approx(k[1], rel=1e-9) and k[0] == pytest.approx(1.03, rel=0.02)
    assert other.ci95_m3s[0] < 1.03 * q0 < other.ci95_m3s[1]
    off = un.monte_carlo_discharge(m, sig, 1.03 * q0, n_draws=300, n_draws_source=80, field_discharge_m3s=0.86 * q0)
    assert off.ci95_m3s == pytest.approx(other.ci95_m3s, rel=1e-9)
    stretched = un.monte_carlo_discharge(m, sig, 1.2 * q0, n_draws=300, n_draws_source=80)
    assert stretched.ci95_m3s[1] == pytest.approx(1.2 * q0)  # without it: only stretched to reach Q


def test_monte_carlo_without_sources_reproduces_q():
    m = _model()
    sig = un.McSigmas(level_m=0, gcp_px=0, gcp_ref_m=0, alpha=0, bed_m=0, filled_rel=0, piv_rel=0, sampling=False)
    r = un.monte_carlo_discharge(m, sig, 8.925, n_draws=50, n_draws_source=20)
    assert r.ci95_m3s == pytest.approx((8.925, 8.925), rel=1e-9)
    assert all(b["share"] == 0 for b in r.budget)


# --------------------------------------------------------------------------------------------- runs and exit 3


def test_run_writes_quality_and_uncertainty_and_exits_3_when_unusable(short_scene, tmp_path, capsys):
    out = tmp_path / "out"
    code, text = _run(short_scene.project_path, out, capsys)
    res = json.loads((out / "result.json").read_text())
    assert code == 0 and res["quality"]["grade"] in ("good", "doubtful")
    lo, hi = res["discharge_ci95_m3s"]
    assert lo <= res["discharge_m3s"] <= hi and res["uncertainty"]["ci95_m3s"] == [lo, hi]
    assert "95 % interval" in text and "not an interval of Q" in text

    def slow_bound(p):
        p.quality.max_surface_speed_ms = 0.5

    for f in out.iterdir():
        if f.name != "piv_cache.npz":
            f.unlink()
    code, text = _run(_variant(short_scene, "bound", slow_bound), out, capsys)
    assert code == 3
    assert "speed_bound" not in text and "exceeds quality.max_surface_speed_ms = 0.5" in text
    for name in ("result.json", "subsections.csv", "mean_field.npz", "section.png", "vectors.png"):
        assert (out / name).is_file(), name
    assert json.loads((out / "result.json").read_text())["quality"]["grade"] == "unusable"


def test_identical_frames_are_unusable(short_scene, tmp_path, capsys):
    cap = cv2.VideoCapture(str(short_scene.video_path))
    ok, frame = cap.read()
    cap.release()
    assert ok
    frames = short_scene.project_path.parent / "still"
    frames.mkdir(exist_ok=True)
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    for i in range(31):
        cv2.imwrite(str(frames / f"f{i:03d}.png"), gray)

    def still(p):
        p.video.path = "still/*.png"
        p.video.frame_interval_s = 1 / 30

    project = _variant(short_scene, "still", still)
    for run in ("first", "PIV reused from the cache"):
        code, text = _run(project, tmp_path / "out", capsys)
        assert code == 3, run
        res = json.loads((tmp_path / "out" / "result.json").read_text())
        codes = {r["code"] for r in res["quality"]["reasons"]}
        assert {"identical_frames", "no_motion"} <= codes, run
    assert res["piv_reused"] is True


def test_a_band_far_below_what_its_depth_suggests_is_in_deficit_and_widens_the_interval():
    depth = np.array([0.2, 0.5, 0.8, 1.0, 1.1, 1.0, 0.8, 0.5, 0.2])
    v = 1.2 * depth ** (2 / 3)
    assert ql.assess(_ev(v, subsection_depth_m=depth)).grade == "good"
    v[5:8] *= 0.5  # glints pull a band down by half
    q = ql.assess(_ev(v, subsection_depth_m=depth))
    r = {x.code: x for x in q.reasons}["velocity_deficit"]
    assert q.grade == "doubtful" and "6 (" in r.message and 0.1 < r.value < 0.3 and r.threshold == 0.03
    assert list(ql.deficit_subsections(v, depth)) == [5, 6, 7]
    assert ql.depth_envelope(v, depth)[6] == pytest.approx(1.2 * 0.8 ** (2 / 3), rel=0.02)


def test_doubted_velocities_widen_the_interval_upward_only():
    m = _model()
    sig = un.McSigmas(level_m=0, gcp_px=0, gcp_ref_m=0, alpha=0, bed_m=0, filled_rel=0, piv_rel=0, sampling=False)
    m.underread_max = 0.5
    r = un.monte_carlo_discharge(m, sig, 8.925, n_draws=400, n_draws_source=50)
    lo, hi = r.ci95_m3s
    assert lo == pytest.approx(8.925, rel=0.02) and hi == pytest.approx(2 * 8.925, rel=0.05)
    assert {b["source"]: b["share"] for b in r.budget}["velocity_sampling"] == pytest.approx(1.0)


def test_an_over_read_widens_the_interval_downward_only():
    """STIV reads slower and disagrees: the velocities may be over-read by up to ``overread_max``; the lower
    bound comes from the draws with it, the upper from those without, and the budget shows it."""
    m = _model()
    sig = un.McSigmas(level_m=0, gcp_px=0, gcp_ref_m=0, alpha=0, bed_m=0, filled_rel=0, piv_rel=0, sampling=False)
    plain = un.monte_carlo_discharge(m, sig, 8.925, n_draws=400, n_draws_source=50)
    m.overread_max = 0.4
    r = un.monte_carlo_discharge(m, sig, 8.925, n_draws=400, n_draws_source=50)
    lo, hi = r.ci95_m3s
    assert lo == pytest.approx(8.925 * (1 - 0.975 * 0.4), rel=0.02) and hi == pytest.approx(plain.ci95_m3s[1])
    assert {b["source"]: b["share"] for b in r.budget}["velocity_sampling"] == pytest.approx(1.0)
    m.underread_max = 0.5  # both: each widens its own side
    lo2, hi2 = un.monte_carlo_discharge(m, sig, 8.925, n_draws=400, n_draws_source=50).ci95_m3s
    assert lo2 == pytest.approx(lo, rel=0.03) and hi2 == pytest.approx(2 * 8.925, rel=0.05)


def test_few_valid_single_pairs_are_only_doubtful_where_the_nodes_were_judged_by_their_ensemble():
    """The faint-glare plan (min_valid_fraction 0) expects few valid single pairs: alone they make the run
    doubtful, not unusable; elsewhere the same fraction is unusable."""
    th = ql.Thresholds()
    plain = ql.check_valid_fraction(_ev(np.full(5, 1.0), valid_fraction_section=0.06), th)
    judged = ql.check_valid_fraction(_ev(np.full(5, 1.0), valid_fraction_section=0.06, ensemble_judged=True), th)
    assert [r.severity for r in plain] == ["unusable"]
    assert [r.severity for r in judged] == ["doubtful"] and "ensemble peak" in judged[0].message
