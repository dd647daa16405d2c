"""ISO 748 and IVE uncertainty (processing/standard_uncertainty.py): hand-computed cases and properties."""

import json

import numpy as np
import pytest

from fieldtool.processing import standard_uncertainty as su


def _uniform(n=5, depth=1.0, v=1.0, alpha=0.85, width=5.0):
    e = np.linspace(0.0, width, n + 1)
    d = np.full(n, depth)
    vv = np.full(n, v)
    q = alpha * np.diff(e) * d * vv
    return e, d, vv, np.zeros(n, bool), q


def test_iso748_by_hand():
    # u_s² = 0.01² + 0.01² + 0.03² ; u_m(5) = 7.5 % ; per vertical (1/5)² · (0.005² + 0.005² + 0.07² + 0.01² + 0.08²)
    e, d, v, f, q = _uniform()
    out = su.iso748(e, d, v, f, q, exposure_s=10.0, sig=su.StandardSigmas(alpha_rel=0.03))
    u2 = 1.1e-3 + 0.075**2 + (0.005**2 + 0.005**2 + 0.07**2 + 0.01**2 + 0.08**2) / 5
    assert out["u_rel"] == pytest.approx(np.sqrt(u2), rel=1e-9)
    assert out["u95_rel"] == pytest.approx(2 * np.sqrt(u2), rel=1e-9)
    Q = q.sum()
    assert out["ci95_m3s"] == pytest.approx([Q * (1 - 2 * np.sqrt(u2)), Q * (1 + 2 * np.sqrt(u2))])
    assert out["rating"] == "poor"
    assert out["components"]["u_m"] == pytest.approx(0.075)


def test_shallow_depth_and_bed_sigma():
    e, d, v, f, q = _uniform(n=1, depth=0.2)
    sig = su.StandardSigmas(bed_m=0.02, u_sm=0, u_so=0, alpha_rel=0)
    out = su.iso748(e, d, v, f, q, 10.0, sig)
    assert out["components"]["u_d"] == pytest.approx(np.sqrt(0.015**2 + (0.02 / 0.2) ** 2))


def test_more_verticals_smaller_u_m_and_u():
    um = [su.u_verticals(n) for n in (3, 5, 8, 10, 15, 20, 25, 30, 35, 50)]
    assert all(a >= b for a, b in zip(um, um[1:], strict=False))
    assert su.u_verticals(12) < su.u_verticals(8)
    u = [su.iso748(*_uniform(n), exposure_s=10.0)["u_rel"] for n in (5, 10, 20, 40)]
    assert all(a > b for a, b in zip(u, u[1:], strict=False))


def test_exposure_from_pairs_shrinks_with_duration():
    rng = np.random.default_rng(1)
    e, d, v, f, q = _uniform(n=10)
    pairs = v + rng.normal(0, 0.2, (400, 10))
    short = su.exposure_u(pairs, v, 5.0, su.StandardSigmas())
    long = su.exposure_u(pairs, v, 80.0, su.StandardSigmas())
    assert np.all(long < short)
    assert short == pytest.approx(0.2 / np.sqrt(5.0), rel=0.15)  # one independent sample a second
    # never more independent samples than pairs
    few = su.exposure_u(pairs[:4], v, 80.0, su.StandardSigmas())
    assert np.median(few) > 2 * np.median(long)
    # no pairs: the default
    assert np.all(su.exposure_u(None, v, 10.0, su.StandardSigmas()) == 0.08)


def test_filled_subsection_raises_both():
    e, d, v, f, q = _uniform(n=10)
    f2 = f.copy()
    f2[3] = True
    assert su.iso748(e, d, v, f2, q, 10.0)["u_rel"] > su.iso748(e, d, v, f, q, 10.0)["u_rel"]
    assert su.ive(e, d, v, f2, q)["u_rel"] > su.ive(e, d, v, f, q)["u_rel"]


def test_ive_by_hand_alternating_velocity():
    # equal spacing: omega = 1/2, residual of an alternating +-eps is 2 eps, divided by 2(1 - 1/2 + 1/4) = 1.5
    n, eps = 9, 0.05
    e = np.linspace(0, 9, n + 1)
    st = 0.5 * (e[:-1] + e[1:])
    d = 1.0 + 0.1 * st  # linear: no depth residual
    v = 1.0 + eps * (-1.0) ** np.arange(n)
    q = 0.85 * np.diff(e) * d * v
    sig = su.StandardSigmas(u_sm=0, u_so=0, alpha_rel=0, u_b=0)
    out = su.ive(e, d, v, np.zeros(n, bool), q, sig)
    assert out["s_depth_m"] == pytest.approx(0.0, abs=1e-12)
    assert out["s_velocity_ms"] == pytest.approx(eps * np.sqrt(8 / 3), rel=1e-9)
    assert out["n_residuals"] == {"depth": n - 2, "velocity": n - 2}
    expect = np.sqrt(np.sum((q / q.sum()) ** 2 * (out["s_velocity_ms"] / v) ** 2))
    assert out["u_rel"] == pytest.approx(expect, rel=1e-9)


def test_ive_recovers_the_noise():
    rng = np.random.default_rng(3)
    n = 400
    e = np.linspace(0, 40, n + 1) + np.r_[0, rng.uniform(-0.02, 0.02, n - 1), 0]  # uneven spacing
    st = 0.5 * (e[:-1] + e[1:])
    d_true = 0.5 + 1.5 * np.sin(np.pi * st / 40)
    v_true = 0.3 + 0.9 * np.sin(np.pi * st / 40) ** 0.5
    d = d_true + rng.normal(0, 0.03, n)
    v = v_true + rng.normal(0, 0.05, n)
    q = 0.85 * np.diff(e) * d * v
    out = su.ive(e, d, v, np.zeros(n, bool), q)
    assert out["s_depth_m"] == pytest.approx(0.03, rel=0.15)
    assert out["s_velocity_ms"] == pytest.approx(0.05, rel=0.15)


def test_ive_floor_and_few_verticals():
    e, d, v, f, q = _uniform(n=2)  # no interior vertical: no residual; the floor applies
    out = su.ive(e, d, v, f, q)
    assert out["n_residuals"]["velocity"] == 0
    assert out["s_velocity_ms"] == pytest.approx(0.01 * 1.0)
    assert np.isfinite(out["u_rel"])


@pytest.mark.parametrize(
    "u95, name",
    [
        (0.015, "excellent"),
        (0.02, "excellent"),
        (0.04, "good"),
        (0.07, "fair"),
        (0.09, "poor"),
        (float("nan"), None),
        (None, None),
    ],
)
def test_rating(u95, name):
    assert su.rating(u95) == name


def test_block_is_strict_json():
    e, d, v, f, q = _uniform(n=12)
    out = su.standard_uncertainty(e, d, v, f, q, 12.0)
    json.dumps(out, allow_nan=False)
    assert set(out) == {"iso748", "ive", "k"}
    zero = su.standard_uncertainty(e, d, v, f, np.zeros(12), 12.0)  # Q = 0: no interval, no NaN
    assert zero["iso748"]["ci95_m3s"] is None
    json.dumps(zero["iso748"]["ci95_m3s"], allow_nan=False)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError):
        su.iso748(np.arange(4.0), np.ones(2), np.ones(2), None, np.ones(2), 1.0)


# ---------------------------------------------------------------------------------------------
# the hooks: result.json, the report, the TUI and the history


def test_run_writes_uncertainty_standard(scene):
    from fieldtool.project.model import load_project
    from fieldtool.records.report import load_result, render_html
    from fieldtool.run.pipeline import run_project

    run_project(load_project(scene / "project.toml"), scene / "out")
    s = json.loads((scene / "out" / "result.json").read_text())
    std = s["uncertainty_standard"]
    q = s["discharge_m3s"]
    for key in ("iso748", "ive"):
        lo, hi = std[key]["ci95_m3s"]
        assert lo < q < hi and std[key]["rating"] in ("excellent", "good", "fair", "poor")
        assert std[key]["u95_rel"] == pytest.approx((hi - lo) / 2 / q)
    assert std["iso748"]["exposure_s"] > 0 and std["iso748"]["n_verticals"] == s["inputs"]["section"]["n_sub"]
    summary, images, subs = load_result(scene / "out")
    html = render_html(summary, images, subs)
    assert "id='standard'" in html and "ISO 748" in html and "IVE" in html


def test_tui_results_line():
    from fieldtool.tui.screens.results import discharge_lines

    s = {
        "discharge_m3s": 2.0,
        "discharge_ci95_m3s": [1.8, 2.2],
        "uncertainty_standard": {
            "iso748": {"u95_rel": 0.06, "ci95_m3s": [1.88, 2.12], "rating": "fair"},
            "ive": {"u95_rel": 0.04, "ci95_m3s": [1.92, 2.08], "rating": "good"},
        },
    }
    line = [x for x in discharge_lines(s) if x.startswith("standard")]
    assert line and "ISO 748 ±6.0 % (fair) 1.880 .. 2.120" in line[0] and "IVE ±4.0 % (good)" in line[0]
    assert not [x for x in discharge_lines({"discharge_m3s": 2.0}) if x.startswith("standard")]


def test_history_migrates_a_schema_1_database(tmp_path):
    import sqlite3

    from fieldtool.records import history as hmod

    db = tmp_path / "old.sqlite"
    c = sqlite3.connect(db)
    c.executescript(hmod._SCHEMA_V1)
    c.execute(
        "INSERT INTO measurements (site, recorded_at, parameters_json, discharge_m3s) "
        "VALUES ('A', '2024-01-01T00:00:00Z', '{}', 3.5)"
    )
    c.execute("PRAGMA user_version = 1")
    c.commit()
    c.close()
    with hmod.History(db) as h:
        assert h.conn.execute("PRAGMA user_version").fetchone()[0] == hmod.SCHEMA_VERSION
        old = h.query(site="A")[0]
        assert old.discharge_m3s == 3.5 and old.grade is None and old.uncertainty_standard == {}
        std = {"iso748": {"u95_rel": 0.07}, "ive": {"u95_rel": 0.05}}
        mid = h.record_summary(
            {
                "discharge_m3s": 2.0,
                "discharge_ci95_m3s": [1.8, 2.3],
                "quality": {"grade": "good"},
                "uncertainty_standard": std,
            },
            site="A",
        )
        m = h.get(mid)
        assert (m.grade, m.discharge_ci95_lo_m3s, m.discharge_ci95_hi_m3s) == ("good", 1.8, 2.3)
        assert m.uncertainty_standard == std
        text = hmod.export_csv(h, h.query(site="A"))
    assert "iso748_u95_rel" in text.splitlines()[0] and ",0.07," in text


def test_read_only_schema_1_history_still_lists(tmp_path, monkeypatch):
    """A history of schema 1 on a read-only disk cannot be migrated; it is still listed (new columns empty)."""
    import sqlite3

    from fieldtool.records import history as hmod

    db = tmp_path / "old.sqlite"
    c = sqlite3.connect(db)
    c.executescript(hmod._SCHEMA_V1)
    c.execute(
        "INSERT INTO measurements (site, recorded_at, parameters_json, discharge_m3s) "
        "VALUES ('A', '2024-01-01T00:00:00Z', '{}', 3.5)"
    )
    c.execute("PRAGMA user_version = 1")
    c.commit()
    c.close()
    monkeypatch.setattr(hmod, "_writable", lambda _p: False)
    with hmod.History(db, create=False) as h:
        assert h.readonly
        m = h.query(site="A")[0]
        assert m.discharge_m3s == 3.5 and m.grade is None and m.uncertainty_standard == {}
        assert h.get(m.id).discharge_ci95_lo_m3s is None
    assert sqlite3.connect(db).execute("PRAGMA user_version").fetchone()[0] == 1  # left as it was
