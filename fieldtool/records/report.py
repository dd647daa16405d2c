"""One report per measurement: a self-contained HTML file (plots embedded as base64 PNG), and
optionally a PDF drawn with matplotlib.

The report is built from a run's output folder (``result.json``, ``subsections.csv`` and the PNG
plots it lists) and, when the run is in the history, its site, video time and reference discharges.
"""

from __future__ import annotations

import base64
import csv
import html
import json
import os
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

from fieldtool import __version__
from fieldtool.errors import InputFileError
from fieldtool.project.model import atomic_write_bytes
from fieldtool.records.history import Measurement, Reference
from fieldtool.records.report_content import (
    COLUMN_NAMES,
    GRADE_COLOURS,
    PLOTS,
    budget_rows,
    discharge_text,
    header_rows,
    parameter_rows,
    result_rows,
    standard_rows,
    subsection_cell,
)
from fieldtool.records.report_content import fmt_value as _f

VIDEO_EMBED_MAX_BYTES = 24 * 2**20  # overlay.mp4 is embedded (base64) up to this size, linked beside the report above


def load_result(result_dir: Path | str) -> tuple[dict, dict[str, bytes], list[dict]]:
    """(summary, {files key: PNG bytes}, subsection rows) from a run's output folder."""
    d = Path(result_dir)
    path = d / "result.json"
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(f"{path}: not found; give the output folder of a run (it holds result.json)") from None
    except (OSError, ValueError) as e:
        raise InputFileError(f"{path}: cannot be read as a run result ({e}); run the project again") from e
    if not isinstance(summary, dict) or not isinstance(summary.get("files") or {}, dict):
        raise InputFileError(
            f"{path}: is not a fieldtool run result (expected a JSON object with 'files'); run the project again"
        )
    files = summary.get("files") or {}
    images = {}
    for key, name in files.items():
        if isinstance(name, str) and name.lower().endswith(".png"):
            f = inside(d, name)
            if f is not None and f.is_file():
                images[key] = f.read_bytes()
    rows: list[dict] = []
    sub = inside(d, str(files.get("subsections", "subsections.csv")))
    if sub is not None and sub.is_file():
        with sub.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    return summary, images, rows


def inside(folder: Path, name: str) -> Path | None:
    """``folder / name`` when it stays inside ``folder`` (no absolute path, no ``..``, no link out), else None.

    ``result.json`` may have been edited by anyone: the report embeds only files of its own folder.
    """
    p = Path(name)
    if not name or p.is_absolute() or ".." in p.parts:
        return None
    root = folder.resolve()
    target = (root / p).resolve()
    return target if root in target.parents else None


def _e(v) -> str:
    return html.escape(str(v))


_CSS = """
body{font-family:"DejaVu Sans",system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:1.5em auto;max-width:1000px;
color:#1f2328;padding:0 1.2em;line-height:1.4}
h1{font-size:1.45em;margin:.2em 0}
h2{font-size:1.1em;border-bottom:1px solid #d0d7de;padding-bottom:.2em;margin-top:1.5em}
.head{display:grid;grid-template-columns:max-content 1fr max-content 1fr;gap:.15em 1.2em;font-size:.95em}
.head dt{color:#57606a} .head dd{margin:0;font-weight:600}
.qbox{border:2px solid #d0d7de;border-radius:8px;padding:.8em 1.1em;margin:1em 0;display:flex;gap:2em;
align-items:center;flex-wrap:wrap} .q{font-size:1.7em;font-weight:700} .ci{font-size:1.05em}
.grade{display:inline-block;padding:.2em .7em;border-radius:1em;color:#fff;font-weight:700;text-transform:uppercase;
letter-spacing:.04em} .reasons{margin:.4em 0 0 1.2em;padding:0} .reasons li{margin:.15em 0}
.muted{color:#57606a;font-size:.88em}
table{border-collapse:collapse;font-size:.9em;margin:.4em 0}
td,th{border:1px solid #d0d7de;padding:.25em .6em;text-align:right}
th{background:#f6f8fa} td.k,th.k{text-align:left} .warn{color:#9a6700}
figure{margin:1em 0;page-break-inside:avoid} figure img{max-width:100%;border:1px solid #d0d7de}
figcaption{font-size:.88em;color:#57606a} figure video{max-width:100%;border:1px solid #d0d7de;background:#000}
@media print{body{margin:0;max-width:none;font-size:10pt} h2{page-break-after:avoid} .qbox{page-break-inside:avoid}}
"""


def _header_html(summary: dict, measurement: Measurement | None) -> list[str]:
    rows = header_rows(summary, measurement)
    out = ["<dl class='head' id='header'>"]
    out += [f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in rows]
    out.append("</dl>")
    return out


def _discharge_html(summary: dict) -> list[str]:
    t = discharge_text(summary)
    out = ["<div class='qbox' id='discharge'>", f"<div><div class='q'>Q = {_e(t['q'])}</div>"]
    if t["ci"]:
        out.append(f"<div class='ci' id='interval'>95 % interval {_e(t['ci'])} ({_e(t['rel'])})</div></div>")
    else:
        out.append(
            "<div class='ci muted' id='interval'>no 95 % interval in this result (computed by newer "
            "fieldtool runs)</div></div>"
        )
    if t["grade"]:
        colour = GRADE_COLOURS.get(t["grade"], "#57606a")
        out.append(f"<div id='quality'><span class='grade' style='background:{colour}'>{_e(t['grade'])}</span>")
        if t["reasons"]:
            out.append(
                "<ul class='reasons'>"
                + "".join(f"<li><b>{_e(sev)}</b>: {_e(msg)}</li>" for sev, msg in t["reasons"])
                + "</ul>"
            )
        else:
            out.append("<div class='muted'>no reason for doubt found</div>")
        out.append("</div>")
    else:
        out.append("<div id='quality' class='muted'>no quality grade in this result</div>")
    out.append("</div>")
    lo, hi = summary.get("discharge_p05_m3s"), summary.get("discharge_p95_m3s")
    if lo is not None and hi is not None:
        out.append(
            f"<p class='muted' id='spread'>Spread of the discharge of single frame pairs (not an interval "
            f"of Q): 5–95 % {_f(lo, '.3f')} – {_f(hi, '.3f')} m³/s over {summary.get('n_pairs', '?')} "
            "frame pairs.</p>"
        )
    std = standard_rows(summary)
    if std:  # the hydrologists' standard uncertainty beside ours (issue 27)
        out.append(
            "<table id='standard'><tr><th class='k'>method (2σ)</th><th>95 % interval</th><th>relative</th>"
            "<th>USGS rating</th></tr>"
        )
        out += [
            f"<tr><td class='k'>{_e(a)}</td><td>{_e(b)}</td><td>{_e(c)}</td><td>{_e(d)}</td></tr>" for a, b, c, d in std
        ]
        out.append("</table>")
    budget = budget_rows(summary)
    if budget:
        out.append(
            "<table id='budget'><tr><th class='k'>uncertainty source</th><th>share of variance</th>"
            "<th>u (m³/s)</th></tr>"
        )
        out += [f"<tr><td class='k'>{_e(a)}</td><td>{_e(b)}</td><td>{_e(c)}</td></tr>" for a, b, c in budget]
        out.append("</table>")
    return out


def _sections_html(summary: dict) -> list[str]:
    """Several sections: each one's discharge, interval and grade, then their mean, std and CV (RIVeR's table)."""
    secs = summary.get("sections") or []
    if not secs:
        return []
    out = [
        "<h2>Sections</h2><table id='sections'><tr><th class='k'>section</th><th>Q (m³/s)</th>"
        "<th>95 % interval (m³/s)</th><th class='k'>grade</th><th>wetted width (m)</th>"
        "<th>mean velocity (m/s)</th></tr>"
    ]
    for e in secs:
        if "error" in e:
            out.append(
                f"<tr><td class='k'>{_e(e.get('name'))}</td><td colspan='5' class='warn'>{_e(e['error'])}</td></tr>"
            )
            continue
        ci = e.get("discharge_ci95_m3s")
        ci_txt = f"{_f(ci[0])} – {_f(ci[1])}" if ci else "–"
        out.append(
            f"<tr><td class='k'>{_e(e.get('name'))}</td><td>{_f(e.get('discharge_m3s'))}</td><td>{ci_txt}</td>"
            f"<td class='k'>{_e(e.get('grade') or '–')}</td><td>{_f(e.get('wetted_width_m'), '.3f')}</td>"
            f"<td>{_f(e.get('mean_velocity_ms'), '.3f')}</td></tr>"
        )
    sm = summary.get("sections_summary") or {}
    if sm:
        cv = sm.get("cv")
        out.append(
            f"<tr><th class='k'>mean of {sm.get('n')}</th><td>{_f(sm.get('mean_m3s'))}</td>"
            f"<td colspan='4'>std {_f(sm.get('std_m3s'))} m³/s, "
            f"CV {_f(100 * cv if cv is not None else None, '.1f', '%')}"
            "</td></tr>"
        )
    out.append("</table>")
    return out


def overlay_video(result_dir: Path | str, summary: dict, report_path: Path | str | None = None) -> bytes | str | None:
    """The run's overlay.mp4 for the report: its bytes (embedded) up to :data:`VIDEO_EMBED_MAX_BYTES`, else its
    path relative to ``report_path`` (linked); None when the run wrote none."""
    d = Path(result_dir)
    name = (summary.get("files") or {}).get("overlay")
    f = inside(d, name) if isinstance(name, str) else None
    if f is None or not f.is_file():
        return None
    if f.stat().st_size <= VIDEO_EMBED_MAX_BYTES:
        return f.read_bytes()
    base = Path(report_path).resolve().parent if report_path is not None else d.resolve()
    return Path(os.path.relpath(f, base)).as_posix()


def _video_html(video: bytes | str | None, summary: dict) -> list[str]:
    """The overlay video in a ``<video>`` element (embedded, or linked when large)."""
    if video is None:
        return []
    info = summary.get("overlay") or {}
    src = f"data:video/mp4;base64,{base64.b64encode(video).decode('ascii')}" if isinstance(video, bytes) else _e(video)
    cap = (
        f"The analysed clip with the per-pair vectors, the section's subsections coloured by surface velocity and "
        f"the running Q; closing card with the final Q, its 95 % interval and the grade "
        f"({_e(info.get('frames', '?'))} frames + {_e(info.get('card_frames', 0))} of the card, "
        f"{_e(info.get('width_px', '?'))}x{_e(info.get('height_px', '?'))}, {_e(info.get('view', ''))} view)."
    )
    return [
        "<h2>Overlay video</h2>",
        f"<figure id='overlay'><video id='overlay-video' controls muted playsinline preload='auto' src='{src}'>"
        f"your browser does not play MP4 video: open overlay.mp4</video><figcaption>{cap}</figcaption></figure>",
    ]


def render_html(
    summary: dict,
    images: dict[str, bytes],
    subsections: list[dict],
    *,
    measurement: Measurement | None = None,
    references: Sequence[Reference] = (),
    title: str | None = None,
    video: bytes | str | None = None,
) -> str:
    """The report as one HTML string with every plot embedded (no external file or network); ``video`` is the
    overlay video (:func:`overlay_video`: bytes embedded, or a relative path linked)."""
    inputs = summary.get("inputs") or {}
    name = title or inputs.get("name") or "measurement"
    q = summary.get("discharge_m3s")
    out = [
        "<!DOCTYPE html>",
        "<html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>fieldtool report — {_e(name)}</title><style>{_CSS}</style></head><body>",
        f"<h1>Discharge measurement — {_e(name)}</h1>",
    ]
    out += _header_html(summary, measurement)
    out += _discharge_html(summary)

    rows = [(k, _e(v)) for k, v in result_rows(summary)]
    out.append("<h2>Result</h2><table id='result'>")
    out += [f"<tr><th class='k'>{k}</th><td>{v}</td></tr>" for k, v in rows]
    out.append("</table>")

    out += _sections_html(summary)

    if references:
        out.append(
            "<h2>Reference discharges</h2><table><tr><th class='k'>method</th><th>Q ref (m³/s)</th>"
            "<th>± (m³/s)</th><th>LSPIV − ref (%)</th><th class='k'>note</th></tr>"
        )
        for r in references:
            err = 100.0 * (q - r.discharge_m3s) / r.discharge_m3s if q is not None else None
            out.append(
                f"<tr><td class='k'>{_e(r.method)}</td><td>{_f(r.discharge_m3s)}</td>"
                f"<td>{_f(r.uncertainty_m3s)}</td><td>{_f(err, '+.2f')}</td><td class='k'>{_e(r.note)}</td></tr>"
            )
        out.append("</table>")

    warnings = summary.get("warnings") or []
    if warnings:
        out.append("<h2>Warnings</h2><ul>" + "".join(f"<li class='warn'>{_e(w)}</li>" for w in warnings) + "</ul>")

    out += _video_html(video, summary)
    out.append("<h2>Figures</h2>")
    captions = dict(PLOTS)
    order = [k for k, _ in PLOTS if k in images] + sorted(k for k in images if k not in captions)
    if not order:
        out.append("<p class='muted'>no plots in the output folder</p>")
    for key in order:
        b64 = base64.b64encode(images[key]).decode("ascii")
        cap = captions.get(key, key.removesuffix("_png").replace("_", " "))
        out.append(
            f"<figure id='plot-{_e(key)}'><img alt='{_e(cap)}' src='data:image/png;base64,{b64}'>"
            f"<figcaption>{_e(cap)}</figcaption></figure>"
        )

    if subsections:
        cols = list(subsections[0].keys())
        out.append(
            "<h2>Subsections</h2><table id='subsections'><tr>"
            + "".join(f"<th>{_e(_COLUMN_NAMES.get(c, c))}</th>" for c in cols)
            + "</tr>"
        )
        for row in subsections:
            out.append("<tr>" + "".join(f"<td>{_e(subsection_cell(c, row.get(c, '')))}</td>" for c in cols) + "</tr>")
        out.append("</table>")

    out.append(
        "<h2>Parameters</h2><table id='inputs'><tr><th class='k'>step</th><th class='k'>parameter</th>"
        "<th class='k'>value</th></tr>"
    )
    out += [
        f"<tr><td class='k'>{_e(a)}</td><td class='k'>{_e(b)}</td><td class='k'>{_e(c)}</td></tr>"
        for a, b, c in parameter_rows(inputs)
    ]
    out.append("</table>")
    if measurement is not None and measurement.input_hash:
        out.append(
            f"<p class='muted'>history id {measurement.id}; input hash (SHA-256 of parameters and input "
            f"files): <code>{_e(measurement.input_hash)}</code></p>"
        )
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    out.append(
        f"<p class='muted'>report written {now} by fieldtool {_e(__version__)}; the run used fieldtool "
        f"{_e(summary.get('fieldtool_version', '?'))}. Every value of the run: result.json.</p></body></html>"
    )
    return "\n".join(out)


_COLUMN_NAMES = COLUMN_NAMES


def render_pdf(
    summary: dict,
    images: dict[str, bytes],
    subsections: list[dict],
    *,
    measurement: Measurement | None = None,
    references: Sequence[Reference] = (),
) -> bytes:
    """The report as PDF bytes (A4), with everything the HTML has (``records.report_pdf``)."""
    from fieldtool.records.report_pdf import render_pdf as _render  # matplotlib only when a PDF is asked for

    return _render(summary, images, subsections, measurement=measurement, references=references, plots=PLOTS)


def write_report(
    result_dir: Path | str,
    out: Path | str | None = None,
    *,
    pdf: bool = False,
    measurement: Measurement | None = None,
    references: Sequence[Reference] = (),
) -> list[Path]:
    """Write ``report.html`` (and ``report.pdf``) for a run's output folder. Returns the paths."""
    result_dir = Path(result_dir)
    summary, images, rows = load_result(result_dir)
    out = Path(out) if out else result_dir / "report.html"
    video = overlay_video(result_dir, summary, out)
    atomic_write_bytes(
        out,
        render_html(summary, images, rows, measurement=measurement, references=references, video=video).encode("utf-8"),
    )
    written = [out]
    if pdf:
        p = out.with_suffix(".pdf")
        atomic_write_bytes(p, render_pdf(summary, images, rows, measurement=measurement, references=references))
        written.append(p)
    return written
