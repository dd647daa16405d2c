"""HTML (and PDF) report of a measurement: from a fake result folder and from a real run."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from fieldtool.cli.main import main
from fieldtool.errors import InputFileError
from fieldtool.records.history import History
from fieldtool.records.report import load_result, render_html, write_report


def png(seed: int) -> bytes:
    img = np.random.default_rng(seed).integers(0, 255, (40, 60, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def fake_result(folder: Path, q: float = 12.3456) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    pngs = {"vectors_png": "vectors.png", "section_png": "section.png", "rectified_png": "rectified.png"}
    for i, name in enumerate(pngs.values()):
        (folder / name).write_bytes(png(i))
    rows = [
        "subsection,station_from_m,station_to_m,area_m2,mean_depth_m,surface_velocity_ms,velocity_filled,discharge_m3s"
    ]
    rows += [f"{k + 1},{k:.4f},{k + 1:.4f},0.5,0.5,1.0,0,{q / 4:.5f}" for k in range(4)]
    (folder / "subsections.csv").write_text("\n".join(rows) + "\n")
    summary = {
        "discharge_m3s": q,
        "discharge_p05_m3s": 11.5,
        "discharge_p95_m3s": 13.25,
        "n_pairs": 29,
        "water_level_m": 10.0,
        "water_level_method": "value",
        "water_level_uncertainty_m": 0.01,
        "wetted_area_m2": 11.86,
        "wetted_width_m": 12.0,
        "mean_velocity_ms": 1.04,
        "alpha": 0.85,
        "warnings": ["subsection 1: velocity filled <from the neighbours>"],
        "fieldtool_version": "0.1.0",
        "files": {**pngs, "subsections": "subsections.csv", "result": "result.json"},
        "inputs": {"name": "river <b>x</b>", "video": {"path": "clip.mp4"}, "piv": {"window_px": 48}},
    }
    (folder / "result.json").write_text(json.dumps(summary))
    return summary


def test_html_has_discharge_plots_table_and_is_self_contained(tmp_path):
    fake_result(tmp_path / "res")
    summary, images, rows = load_result(tmp_path / "res")
    html = render_html(summary, images, rows)
    assert re.search(r"Q = 12\.346 m³/s", html)
    assert "11.500 – 13.250 m³/s" in html and "29 frame pairs" in html
    embedded = re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", html)
    assert sorted(base64.b64decode(e) for e in embedded) == sorted(png(i) for i in range(3))
    assert html.index("plot-vectors_png") < html.index("plot-rectified_png") < html.index("plot-section_png")
    table = html[html.index("id='subsections'") :]
    assert table[: table.index("</table>")].count("<tr>") == 5
    assert "Interrogation window" in html and "48 px" in html and "window_px" not in html
    # nothing external, and user text escaped
    assert not re.search(r"(src|href)=['\"](?!data:)", html)
    assert "<b>x</b>" not in html and "river &lt;b&gt;x&lt;/b&gt;" in html
    assert "&lt;from the neighbours&gt;" in html


def test_write_report_html_pdf_and_cli(tmp_path, capsys):
    fake_result(tmp_path / "res")
    paths = write_report(tmp_path / "res", pdf=True)
    assert [p.name for p in paths] == ["report.html", "report.pdf"]
    assert paths[1].read_bytes()[:5] == b"%PDF-"
    assert "12.346" in paths[0].read_text()

    # from the history: site, time and the reference with its error
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        s, _, _ = load_result(tmp_path / "res")
        mid = h.record_summary(
            s, site="bridge", output_dir=(tmp_path / "res").resolve(), video_time=("2024-05-01T08:00:00Z", "container")
        )
        h.add_reference(mid, 12.0, "adcp")
    out = tmp_path / "r.html"
    assert main(["report", "--id", str(mid), "--db", str(db), "--out", str(out)]) == 0
    html = out.read_text()
    assert "bridge" in html and "2024-05-01 08:00:00 UTC (from the video container)" in html and "adcp" in html
    assert "+2.88" in html  # (12.3456 - 12) / 12
    # by folder: the history entry is found by its output folder
    assert main(["report", str(tmp_path / "res"), "--db", str(db)]) == 0
    assert "bridge" in (tmp_path / "res" / "report.html").read_text()


def test_missing_result(tmp_path, capsys):
    with pytest.raises(InputFileError, match="result.json"):
        write_report(tmp_path)
    assert main(["report", str(tmp_path), "--db", str(tmp_path / "none.sqlite")]) == 2
    assert "result.json" in capsys.readouterr().err


@pytest.mark.slow
def test_report_of_a_real_run(short_scene, tmp_path):
    from fieldtool.project.model import load_project
    from fieldtool.run.pipeline import run_project

    r = run_project(load_project(short_scene.project_path), tmp_path / "out")
    (html_path,) = write_report(tmp_path / "out")
    html = html_path.read_text()
    assert f"Q = {r.discharge.discharge_m3s:.3f} m³/s" in html
    n_png = sum(1 for v in r.files.values() if str(v).endswith(".png"))
    assert n_png >= 5 and html.count("data:image/png;base64,") == n_png
    assert "plot-profile_png" in html and "plot-gcp_png" in html  # profile with its band, GCPs with residuals
    head = html[html.index("id='header'") : html.index("id='discharge'")]
    assert "river.mp4" in head and "1280 × 720 px" in head and "30 frames/s" in head
    profile = (tmp_path / "out" / "section_profile.csv").read_text().splitlines()
    assert len(profile) == 1 + len(r.discharge.area_m2)
    rows = [[float(x) if x else float("nan") for x in line.split(",")[:5]] for line in profile[1:]]
    # a subsection PIV did not measure (filled, or at an edge STIV's alone) has no band of its own
    measured = [r for r in rows if not r[2] and np.isfinite(r[3])]
    assert len(measured) >= len(rows) - 2
    assert all(lo <= v <= hi for _, v, _, lo, hi in measured if v > 0.3)  # the mean lies in the pairs' band
    assert html.count("<tr>") >= len(r.discharge.area_m2)
    used = (r.stiv or {}).get("velocity_source_used", "piv")  # which velocities Q is of, said beside Q
    said = {"piv": "<td>PIV", "combined": "<td>PIV and STIV combined per subsection (PIV alone "}[used]
    assert "Surface velocities" in html and said in html


def test_report_embeds_only_images_inside_the_result_folder(tmp_path):
    """result.json "files" naming ../../secret_plot.png, an absolute path or a link out is not embedded."""
    secret = png(99)
    (tmp_path / "secret_plot.png").write_bytes(secret)
    res = tmp_path / "a" / "res"
    summary = fake_result(res)
    (res / "out_link.png").symlink_to(tmp_path / "secret_plot.png")
    summary["files"].update(
        {
            "secret_png": "../../secret_plot.png",
            "abs_png": str(tmp_path / "secret_plot.png"),
            "link_png": "out_link.png",
            "subsections": "../../../etc/passwd",
        }
    )
    (res / "result.json").write_text(json.dumps(summary))
    _, images, rows = load_result(res)
    assert set(images) == {"vectors_png", "section_png", "rectified_png"}
    assert secret not in images.values() and rows == []
    (html_path,) = write_report(res)
    assert base64.b64encode(secret).decode() not in html_path.read_text()


@pytest.mark.parametrize("content", ["[1, 2]", '"x"', "null"])
def test_a_result_that_is_not_an_object_is_refused(tmp_path, content):
    (tmp_path / "result.json").write_text(content)
    with pytest.raises(InputFileError, match="result.json"):
        load_result(tmp_path)


def test_header_interval_grade_reasons_and_readable_parameters(tmp_path):
    """The quality helper's keys are shown (Q ± 95 %, grade, reasons); internal keys are not."""
    s = fake_result(tmp_path / "res")
    s["inputs"].update(
        {
            "operator": "A. Hydro",
            "station": "L-0042",
            "site": "weir",
            "water_level": {"method": "image", "edges_px": [[1.0, 2.0], [3.0, 4.0]]},
            "rerun": {"mode": "off", "path": "run.rrd"},
            "step": "results",
        }
    )
    s["video"] = {
        "file": "clip.mp4",
        "recorded_utc": "2024-05-01T08:00:00Z",
        "recorded_source": "container",
        "width_px": 1920,
        "height_px": 1080,
        "fps": 29.97,
        "n_frames": 300,
        "duration_s": 10.01,
        "start_s": 0.0,
        "end_s": 8.0,
    }
    s["discharge_ci95_m3s"] = [11.8, 12.9]
    s["quality"] = {
        "grade": "doubtful",
        "reasons": [
            {
                "code": "filled",
                "severity": "doubtful",
                "message": "4 of 15 subsections filled from neighbours",
                "value": 0.27,
                "threshold": 0.2,
            }
        ],
    }
    html = render_html(s, {}, [])
    head = html[html.index("id='header'") : html.index("id='discharge'")]
    for text in (
        "weir",
        "L-0042",
        "A. Hydro",
        "clip.mp4",
        "2024-05-01 08:00:00 UTC (from the video container)",
        "10.01 s",
        "1920 × 1080 px",
        "29.97 frames/s",
    ):
        assert text in head, text
    box = html[html.index("id='discharge'") : html.index("<h2>")]
    assert "95 % interval 11.800 – 12.900 m³/s (± 4.5 %)" in box
    assert ">doubtful<" in box and "4 of 15 subsections filled from neighbours (value 0.27, limit 0.2)" in box
    for internal in ("edges_px", "rerun", "run.rrd", "results"):
        assert internal not in html[html.index("id='inputs'") :], internal
    assert "water edges picked on the frame" in html
    # the interval from the uncertainty block alone, and nothing when neither exists
    del s["discharge_ci95_m3s"]
    s["uncertainty"] = {"ci95_m3s": [11.0, 13.0], "budget": [{"source": "water_level", "share": 0.6, "u_m3s": 0.3}]}
    html = render_html(s, {}, [])
    assert "11.000 – 13.000 m³/s" in html and "water level" in html[html.index("id='budget'") :]
    s.pop("uncertainty"), s.pop("quality")
    html = render_html(s, {}, [])
    assert "no 95 % interval in this result" in html and "no quality grade" in html


def _pdf_text(pdf_bytes: bytes, tmp_path) -> str:
    """The PDF's text (pdftotext from poppler-utils, else pypdf)."""
    import shutil
    import subprocess

    f = tmp_path / "r.pdf"
    f.write_bytes(pdf_bytes)
    if shutil.which("pdftotext"):
        return subprocess.run(["pdftotext", "-layout", str(f), "-"], capture_output=True, text=True, check=True).stdout
    pypdf = pytest.importorskip("pypdf", reason="no pdftotext (apt poppler-utils) and no pypdf to read the PDF")
    return "\n".join(p.extract_text() for p in pypdf.PdfReader(str(f)).pages)


def test_pdf_carries_what_the_html_has(tmp_path):
    """Issue 25: budget, result table (valid fraction, pairs, GCP RMS, filled), warnings, STIV column,
    readable subsection headers and "filled" as yes / no, in the PDF's own text."""
    from fieldtool.records.report import render_pdf

    s = fake_result(tmp_path / "res")
    s.update(
        {
            "valid_fraction_mean": 0.73,
            "subsections_filled": 1,
            "ortho_residual_m": 0.0123,
            "section_length_m": 11.5,
            "discharge_ci95_m3s": [11.8, 12.9],
            "quality": {
                "grade": "doubtful",
                "reasons": [{"severity": "doubtful", "code": "x", "message": "see the uncertainty budget"}],
            },
            "uncertainty": {
                "ci95_m3s": [11.8, 12.9],
                "budget": [
                    {"source": "water_level", "share": 0.61, "u_m3s": 0.3},
                    {"source": "velocity_index", "share": 0.39, "u_m3s": 0.2},
                ],
            },
            "warnings": ["subsection 1: velocity filled from the neighbours", "second warning here"],
        }
    )
    rows = [
        {
            "subsection": str(k + 1),
            "station_from_m": f"{k:.4f}",
            "station_to_m": f"{k + 1:.4f}",
            "area_m2": "0.50000",
            "mean_depth_m": "0.5000",
            "surface_velocity_ms": "1.00000",
            "velocity_filled": "1" if k == 0 else "0",
            "discharge_m3s": "3.08640",
            "stiv_velocity_ms": "" if k == 0 else "0.98765",
        }
        for k in range(4)
    ]
    text = _pdf_text(render_pdf(s, {}, rows), tmp_path)
    flat = " ".join(text.split())
    for want in (
        "Uncertainty budget",
        "water level",
        "velocity index α",
        "61 %",
        "0.300 m³/s",
        "Mean valid vector fraction 0.73",
        "Frame pairs 29",
        "GCP fit residual (RMS) 12.3 mm",
        "Subsections with filled velocity 1",
        "Section length 11.500 m",
        "Warnings",
        "subsection 1: velocity filled from the neighbours",
        "second warning here",
        "STIV",
        "0.98765",
        "95 % interval 11.800 – 12.900 m³/s",
        "DOUBTFUL",
    ):
        assert want in flat, want
    # the subsections table: headers on their own lines, one row per subsection, filled as yes / no
    lines = text.splitlines()
    data = [ln.split() for ln in lines if re.match(r"^\s*[1-4]\s+\d\.\d{4}\s", ln)]
    assert len(data) == 4, lines
    assert [r[6] for r in data] == ["yes", "no", "no", "no"]
    assert data[0][-1] == "–" and data[1][-1] == "0.98765"
    head = next(i for i, ln in enumerate(lines) if "from" in ln and "to" in ln and "area" in ln)
    assert all(len(w) < 14 for w in lines[head].split()), lines[head]  # no two headers run together


def test_velocities_said_for_new_old_and_stiv_less_results():
    """The velocities line (report, terminal, TUI) reads result.json's stiv block: velocity_source_used since the
    auto default; a result written before it (no "auto" then) had the source in velocity_source itself."""
    from fieldtool.records.report_content import velocities_text, velocities_used

    new = {
        "velocity_source": "auto",
        "velocity_source_used": "combined",
        "discharge_piv_m3s": 1.25,
        "discharge_m3s": 1.2,
    }
    assert (
        velocities_text({"stiv": new})
        == "PIV and STIV combined per subsection (PIV alone 1.250 m³/s, STIV alone 1.200 m³/s)"
    )
    assert velocities_text({"stiv": new}, short=True) == "PIV+STIV"
    disagree = {"velocity_source": "auto", "velocity_source_used": "piv", "disagreement_reason": {"code": "x"}}
    assert velocities_text({"stiv": disagree}) == "PIV (STIV disagrees: not combined)"
    assert velocities_used({"velocity_source": "stiv"}) == "stiv"  # stop 51's result.json
    assert velocities_text({"stiv": {"velocity_source": "combined"}}).startswith("PIV and STIV combined")
    assert velocities_used(None) == "piv" and velocities_text({"stiv": None}) == "PIV"
