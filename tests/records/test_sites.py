"""Sites: round-trip, unknown site, and a second visit computed from a site with only a video and a level."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest

from fieldtool.cli.main import main
from fieldtool.errors import InputFileError, ParameterError
from fieldtool.project.model import load_project, project_from_dict, project_to_dict, save_project
from fieldtool.records.sites import create_site, list_sites, load_site, new_measurement, sites_dir

XS = "station_m,elevation_m\n0,11\n2,10\n4,9.2\n8,9.0\n12,9.4\n14,10.1\n16,11\n"
CALIB = b'{"lens": {"camera_matrix": [[1000, 0, 640], [0, 1000, 360], [0, 0, 1]]}}\n'


def make_project(folder: Path) -> Path:
    """A project with every kind of site input, and per-visit inputs (video, level, edge picks)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "section.csv").write_text(XS)
    (folder / "lens.json").write_bytes(CALIB)
    (folder / "clip.mp4").write_bytes(b"not decoded here")
    d = {
        "name": "station 7, 2024-05-01",
        "step": "piv",
        "video": {"path": "clip.mp4", "start_s": 1.0, "end_s": 6.0, "step": 2},
        "cross_section": {"path": "section.csv"},
        "calibration": {"path": "lens.json", "checkerboard_video": "board.mp4", "square_mm": 25.0},
        "stabilize": {"enabled": True, "regions_px": [[0.0, 0.0, 100.0, 80.0], [1100.0, 0.0, 1270.0, 90.0]]},
        "ortho": {
            "method": "distances",
            "gcp_px": [[100.0, 600.0], [300.0, 200.0], [900.0, 210.0], [1150.0, 620.0]],
            "distances_m": [8.0, 13.6, 8.0, 13.6, 15.78, 15.78],
        },
        "water_level": {"method": "value", "value_m": 10.05, "uncertainty_m": 0.01, "edges_px": [[5.0, 6.0]]},
        "roi": {
            "rect_px": [200.0, 150.0, 1000.0, 650.0],
            "masks_px": [[[300.0, 300.0], [350.0, 300.0], [320.0, 350.0]]],
        },
        "filters": [{"name": "clahe", "clip_limit": 2.0}],
        "piv": {"window_px": 48, "overlap_px": 24, "passes": 2, "snr_min": 1.5},
        "section": {"points_px": [[250.0, 500.0], [950.0, 480.0]], "n_sub": 12, "alpha": 0.82},
    }
    path = folder / "project.toml"
    save_project(project_from_dict(d, folder), path)
    return path


PER_VISIT = {
    ("video", "path"),
    ("water_level", "value_m"),
    ("water_level", "edges_px"),
    ("calibration", "checkerboard_video"),
}


def test_site_round_trip(tmp_path):
    src = make_project(tmp_path / "first_visit")
    proj = load_project(src)
    root = tmp_path / "sites"
    site = create_site("station-7", proj, root, description="left bank, datum NAP", source=str(src))
    # files copied byte for byte into the site folder
    assert (site.folder / "cross_section.csv").read_text() == XS
    assert (site.folder / "calibration.json").read_bytes() == CALIB
    again = load_site("station-7", root)
    assert again.project == site.project and again.description == "left bank, datum NAP"
    assert [s.name for s in list_sites(root)] == ["station-7"]

    tmpl = project_to_dict(again.template())
    orig = project_to_dict(proj)
    for table, content in orig.items():
        if not isinstance(content, dict):
            continue
        for key, value in content.items():
            if (table, key) in PER_VISIT:
                assert key not in tmpl[table] or tmpl[table][key] in ("", [], None), (table, key)
            elif (table, key) == ("cross_section", "path"):
                assert tmpl[table][key] == "cross_section.csv"
            elif (table, key) == ("calibration", "path"):
                assert tmpl[table][key] == "calibration.json"
            else:
                assert tmpl[table][key] == value, (table, key)
    assert tmpl["filters"] == orig["filters"]

    # a new visit: only the video and the level are new
    video = tmp_path / "visit2" / "clip2.mp4"
    video.parent.mkdir()
    video.write_bytes(b"second video")
    p = new_measurement(again, video, 9.87, tmp_path / "visit2", level_uncertainty_m=0.02)
    new = load_project(p)
    assert new.resolve(new.video.path) == video
    assert new.water_level.method == "value" and new.water_level.value_m == 9.87
    assert new.water_level.uncertainty_m == 0.02
    assert new.resolve(new.cross_section.path).read_text() == XS
    assert new.resolve(new.calibration.path).read_bytes() == CALIB
    assert new.site == "station-7"  # the visit knows its site (for `fieldtool run --record`)
    nd, od = project_to_dict(new), copy.deepcopy(orig)
    for d in (nd, od):
        for table, key in PER_VISIT | {
            ("cross_section", "path"),
            ("calibration", "path"),
            ("water_level", "uncertainty_m"),
        }:
            d[table].pop(key, None)
        d.pop("name"), d.pop("step"), d.pop("site")
    assert nd == od

    # replacing needs --force, and keeps the creation time
    with pytest.raises(ParameterError, match="already exists"):
        create_site("station-7", proj, root)
    replaced = create_site("station-7", proj, root, force=True, description="moved gauge")
    assert replaced.created_at == site.created_at
    with pytest.raises(InputFileError, match="already exists"):
        new_measurement(again, video, 9.9, tmp_path / "visit2")


def test_site_toml_is_plain_toml(tmp_path):
    proj = load_project(make_project(tmp_path / "p"))
    site = create_site("s1", proj, tmp_path / "sites")
    data = tomllib.loads((site.folder / "site.toml").read_text())
    assert data["site"]["name"] == "s1"
    assert data["project"]["ortho"]["distances_m"] == [8.0, 13.6, 8.0, 13.6, 15.78, 15.78]
    assert "path" not in data["project"]["video"]


def test_bad_names_unknown_site_and_missing_level(tmp_path, monkeypatch, capsys):
    root = tmp_path / "sites"
    monkeypatch.setenv("FIELDTOOL_SITES", str(root))
    assert sites_dir() == root
    proj = load_project(make_project(tmp_path / "p"))
    with pytest.raises(ParameterError, match="site name"):
        create_site("../evil", proj, root)
    with pytest.raises(ParameterError, match="no sites in"):
        load_site("nowhere", root)
    create_site("geul", proj, root)
    with pytest.raises(ParameterError, match="'nowhere' not found.*known sites: geul"):
        load_site("nowhere", root)
    assert main(["site", "show", "nowhere"]) == 2
    assert "known sites: geul" in capsys.readouterr().err
    assert main(["site", "new-measurement", "nowhere", "--video", "x.mp4", "--level", "1"]) == 2
    video = tmp_path / "v.mp4"
    video.write_bytes(b"v")
    assert main(["site", "new-measurement", "geul", "--video", str(video), "--out", str(tmp_path / "m")]) == 2
    assert "--level" in capsys.readouterr().err
    # a site without a cross-section is refused
    bare = project_from_dict({"name": "x"}, tmp_path)
    with pytest.raises(ParameterError, match="cross-section"):
        create_site("bare", bare, root)


def test_site_cli(tmp_path, capsys):
    src = make_project(tmp_path / "p")
    root = tmp_path / "sites"
    assert main(["site", "create", "st7", "--from", str(src), "--sites", str(root), "--description", "bridge"]) == 0
    assert main(["site", "list", "--sites", str(root)]) == 0
    assert "st7" in capsys.readouterr().out
    assert main(["site", "show", "st7", "--sites", str(root)]) == 0
    out = capsys.readouterr().out
    assert "lowest bed 9.000 m" in out and "4 GCPs" in out and "2 stable region(s)" in out
    v = tmp_path / "new.mp4"
    v.write_bytes(b"v")
    assert (
        main(
            [
                "site",
                "new-measurement",
                "st7",
                "--sites",
                str(root),
                "--video",
                str(v),
                "--level",
                "9.5",
                "--out",
                str(tmp_path / "visit"),
            ]
        )
        == 0
    )
    assert load_project(tmp_path / "visit" / "project.toml").water_level.value_m == 9.5


@pytest.mark.slow
def test_second_visit_from_site(short_scene, tmp_path):
    """Site from visit 1; visit 2 (another flow, another seed) from the site with only its video and
    level gives visit 2's true discharge; visit 1's own video through the site reproduces visit 1."""
    from fieldtool.run.pipeline import run_project
    from fieldtool.synthetic import presets, render_scene

    first = load_project(short_scene.project_path)
    q1 = run_project(first).discharge.discharge_m3s
    site = create_site("demo", first, tmp_path / "sites")

    p1 = new_measurement(site, short_scene.video_path, short_scene.water_level_m, tmp_path / "again")
    assert run_project(load_project(p1)).discharge.discharge_m3s == pytest.approx(q1, rel=1e-9)

    truth2 = render_scene(presets.get("oblique", duration_s=1.2, seed=3, river__u_max_ms=0.8), tmp_path / "v2")
    p2 = new_measurement(site, truth2.video_path, truth2.water_level_m, tmp_path / "visit2")
    r2 = run_project(load_project(p2))
    q2 = r2.discharge.discharge_m3s
    assert q2 == pytest.approx(truth2.discharge_m3s, rel=0.08)
    assert q2 / q1 == pytest.approx(truth2.discharge_m3s / short_scene.discharge_m3s, rel=0.05)
    assert r2.summary()["water_level_m"] == truth2.water_level_m


def test_site_from_a_result_json(tmp_path):
    import json

    from fieldtool.records.sites import load_site_project

    src = make_project(tmp_path / "p")
    proj = load_project(src)
    (tmp_path / "p" / "out").mkdir()
    res = tmp_path / "p" / "out" / "result.json"
    res.write_text(json.dumps({"discharge_m3s": 1.0, "inputs": project_to_dict(proj)}))
    a = create_site("a", load_site_project(src), tmp_path / "sites")
    b = create_site("b", load_site_project(res), tmp_path / "sites")
    assert a.project == b.project
    res.write_text("{}")
    with pytest.raises(InputFileError, match="inputs"):
        load_site_project(res)
