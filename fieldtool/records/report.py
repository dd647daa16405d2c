"""One report per measurement: a self-contained HTML file (plots embedded as base64 PNG), and
optionally a PDF drawn with matplotlib.

The report is built from a run's output folder (``result.json``, ``subsections.csv`` and the PNG
plots it lists) and, when the run is in the history, its site, video time and reference discharges.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
from datetime import datetime, timezone
from pathlib import Path

from .. import __version__
from ..errors import InputFileError
from ..project import atomic_write_bytes
from .history import Measurement, Reference

# plots of result.json "files", in report order, with captions
PLOTS = (
    ("vectors_png", "Surface velocity vectors on the first frame"),
    ("rectified_png", "Rectified image with the velocity field (world metres)"),
    ("section_png", "Cross-section, water level and subsection velocities / discharges"),
    ("water_level_png", "Water level determination"),
    ("stabilization_png", "Stabilisation"),
)


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
        raise InputFileError(f"{path}: is not a fieldtool run result (expected a JSON object with 'files'); run "
                             "the project again")
    files = summary.get("files") or {}
    images = {}
    for key, name in files.items():
        if isinstance(name, str) and name.lower().endswith(".png") and (d / name).is_file():
            images[key] = (d / name).read_bytes()
    rows: list[dict] = []
    sub = d / str(files.get("subsections", "subsections.csv"))
    if sub.is_file():
        with sub.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    return summary, images, rows


def _f(v, fmt: str = ".4f", unit: str = "") -> str:
    if v is None:
        return "–"
    try:
        return f"{float(v):{fmt}}{(' ' + unit) if unit else ''}"
    except (TypeError, ValueError):
        return html.escape(str(v))


def _e(v) -> str:
    return html.escape(str(v))


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em} h2{font-size:1.15em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
.q{font-size:1.6em;font-weight:600;margin:.4em 0} .muted{color:#666;font-size:.9em}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3} td.k,th.k{text-align:left} .warn{color:#8a4b00}
figure{margin:1em 0} figure img{max-width:100%;border:1px solid #ddd} figcaption{font-size:.9em;color:#555}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto;font-size:.85em}
@media print{body{margin:0;max-width:none} figure{page-break-inside:avoid}}
"""


def render_html(summary: dict, images: dict[str, bytes], subsections: list[dict], *,
                measurement: Measurement | None = None, references: list[Reference] = (),
                title: str | None = None) -> str:
    """The report as one HTML string with every plot embedded (no external file or network)."""
    inputs = summary.get("inputs") or {}
    name = title or inputs.get("name") or "measurement"
    q = summary.get("discharge_m3s")
    out = ["<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>",
           f"<title>fieldtool report — {_e(name)}</title><style>{_CSS}</style></head><body>",
           f"<h1>Discharge measurement — {_e(name)}</h1>"]
    sub = []
    if measurement is not None:
        sub.append(f"site <b>{_e(measurement.site or '–')}</b>")
        if measurement.video_time:
            sub.append(f"video taken {_e(measurement.video_time)} ({_e(measurement.video_time_source)})")
        sub.append(f"history id {measurement.id}")
    sub.append(f"fieldtool {_e(summary.get('fieldtool_version', '?'))}")
    out.append(f"<p class='muted'>{' · '.join(sub)}</p>")

    out.append(f"<p class='q' id='discharge'>Q = {_f(q, '.4f')} m³/s</p>")
    lo, hi = summary.get("discharge_p05_m3s"), summary.get("discharge_p95_m3s")
    if lo is not None and hi is not None:
        out.append(f"<p id='spread'>spread over {summary.get('n_pairs', '?')} frame pairs (5–95 %): "
                   f"{_f(lo)} – {_f(hi)} m³/s; median of pairs {_f(summary.get('discharge_pairs_median_m3s'))} m³/s</p>")

    rows = [
        ("Water level", f"{_f(summary.get('water_level_m'), '.3f', 'm')} ({_e(summary.get('water_level_method', '?'))}, "
                        f"± {_f(summary.get('water_level_uncertainty_m'), '.3f', 'm')})"),
        ("Wetted area", _f(summary.get("wetted_area_m2"), ".3f", "m²")),
        ("Wetted width", _f(summary.get("wetted_width_m"), ".3f", "m")),
        ("Mean velocity", _f(summary.get("mean_velocity_ms"), ".4f", "m/s")),
        ("Velocity index α", _f(summary.get("alpha"), ".3f") + (" (default for the mean depth)"
                                                                 if summary.get("alpha_default") else " (given)")),
        ("Section length", _f(summary.get("section_length_m"), ".3f", "m")),
        ("Frame pairs", _e(summary.get("n_pairs", "–"))),
        ("Mean valid vector fraction", _f(summary.get("valid_fraction_mean"), ".3f")),
        ("Subsections with filled velocity", _e(summary.get("subsections_filled", "–"))),
        ("Orthorectification", f"{_e(summary.get('ortho_method', '?'))}, residual "
                               f"{_f(summary.get('ortho_residual_m'), '.4f', 'm')}"),
    ]
    out.append("<h2>Result</h2><table>")
    out += [f"<tr><th class='k'>{k}</th><td>{v}</td></tr>" for k, v in rows]
    out.append("</table>")

    if references:
        out.append("<h2>Reference discharges</h2><table><tr><th class='k'>method</th><th>Q ref (m³/s)</th>"
                   "<th>± (m³/s)</th><th>LSPIV − ref (%)</th><th class='k'>note</th></tr>")
        for r in references:
            err = 100.0 * (q - r.discharge_m3s) / r.discharge_m3s if q is not None else None
            out.append(f"<tr><td class='k'>{_e(r.method)}</td><td>{_f(r.discharge_m3s)}</td>"
                       f"<td>{_f(r.uncertainty_m3s)}</td><td>{_f(err, '+.2f')}</td><td class='k'>{_e(r.note)}</td></tr>")
        out.append("</table>")

    warnings = summary.get("warnings") or []
    if warnings:
        out.append("<h2>Warnings</h2><ul>" + "".join(f"<li class='warn'>{_e(w)}</li>" for w in warnings) + "</ul>")

    out.append("<h2>Plots</h2>")
    captions = dict(PLOTS)
    order = [k for k, _ in PLOTS if k in images] + sorted(k for k in images if k not in captions)
    if not order:
        out.append("<p class='muted'>no plots in the output folder</p>")
    for key in order:
        b64 = base64.b64encode(images[key]).decode("ascii")
        cap = captions.get(key, key.removesuffix("_png").replace("_", " "))
        out.append(f"<figure id='plot-{_e(key)}'><img alt='{_e(cap)}' src='data:image/png;base64,{b64}'>"
                   f"<figcaption>{_e(cap)}</figcaption></figure>")

    if subsections:
        cols = list(subsections[0].keys())
        out.append("<h2>Subsections</h2><table id='subsections'><tr>" + "".join(f"<th>{_e(c)}</th>" for c in cols)
                   + "</tr>")
        for r in subsections:
            out.append("<tr>" + "".join(f"<td>{_e(r.get(c, ''))}</td>" for c in cols) + "</tr>")
        out.append("</table>")

    out.append("<h2>Inputs and parameters</h2>")
    out += _inputs_html(inputs)
    if measurement is not None and measurement.input_hash:
        out.append(f"<p class='muted'>input hash (SHA-256 of parameters and input files): "
                   f"<code>{_e(measurement.input_hash)}</code></p>")
    if summary.get("stabilization"):
        out.append("<h3>Stabilisation</h3><pre>" + _e(json.dumps(summary["stabilization"], indent=2)) + "</pre>")
    if summary.get("timings_s"):
        t = summary["timings_s"]
        out.append("<p class='muted'>timings: " + ", ".join(f"{_e(k)} {_f(v, '.2f')} s" for k, v in t.items()) + "</p>")
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out.append(f"<p class='muted'>report written {now} by fieldtool {_e(__version__)}</p></body></html>")
    return "\n".join(out)


def _inputs_html(inputs: dict) -> list[str]:
    out = ["<table id='inputs'>"]
    scalars = {k: v for k, v in inputs.items() if not isinstance(v, (dict, list))}
    for k, v in scalars.items():
        out.append(f"<tr><th class='k'>{_e(k)}</th><td class='k' colspan='2'>{_e(v)}</td></tr>")
    for table, content in inputs.items():
        if isinstance(content, dict):
            for i, (k, v) in enumerate(content.items()):
                head = f"<th class='k' rowspan='{len(content)}'>[{_e(table)}]</th>" if i == 0 else ""
                val = json.dumps(v) if isinstance(v, (list, dict)) else v
                out.append(f"<tr>{head}<td class='k'>{_e(k)}</td><td class='k'>{_e(val)}</td></tr>")
        elif isinstance(content, list):
            out.append(f"<tr><th class='k'>[{_e(table)}]</th><td class='k' colspan='2'>{_e(json.dumps(content))}</td></tr>")
    out.append("</table>")
    return out


def render_pdf(summary: dict, images: dict[str, bytes], subsections: list[dict], *,
               measurement: Measurement | None = None, references: list[Reference] = ()) -> bytes:
    """The report as PDF bytes: a summary page, then one page per plot (matplotlib)."""
    import matplotlib.image as mpimg
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure

    inputs = summary.get("inputs") or {}
    q = summary.get("discharge_m3s")
    lines = [f"Discharge measurement — {inputs.get('name', 'measurement')}"]
    if measurement is not None:
        lines.append(f"site {measurement.site or '-'}, video {measurement.video_time or '?'}, history id {measurement.id}")
    lines += ["",
              f"Q = {_f(q)} m³/s   (5–95 % of pairs: {_f(summary.get('discharge_p05_m3s'))} – "
              f"{_f(summary.get('discharge_p95_m3s'))} m³/s)",
              f"water level {_f(summary.get('water_level_m'), '.3f')} m ({summary.get('water_level_method', '?')})",
              f"wetted area {_f(summary.get('wetted_area_m2'), '.3f')} m²,  width {_f(summary.get('wetted_width_m'), '.3f')} m",
              f"mean velocity {_f(summary.get('mean_velocity_ms'))} m/s,  alpha {_f(summary.get('alpha'), '.3f')}",
              f"fieldtool {summary.get('fieldtool_version', '?')}"]
    for r in references:
        lines.append(f"reference {r.method}: {_f(r.discharge_m3s)} m³/s")
    for w in summary.get("warnings") or []:
        lines.append(f"warning: {w}")
    buf = io.BytesIO()
    with PdfPages(buf) as pdf:
        fig = Figure(figsize=(8.27, 11.69))
        fig.text(0.06, 0.96, "\n".join(lines), va="top", family="sans-serif", fontsize=10, wrap=True)
        if subsections:
            cols = ["subsection", "station_from_m", "station_to_m", "area_m2", "surface_velocity_ms", "discharge_m3s"]
            cols = [c for c in cols if c in subsections[0]]
            ax = fig.add_axes([0.06, 0.05, 0.88, 0.55])
            ax.axis("off")
            tab = ax.table(cellText=[[r[c] for c in cols] for r in subsections], colLabels=cols, loc="upper center")
            tab.auto_set_font_size(False)
            tab.set_fontsize(7)
        pdf.savefig(fig)
        captions = dict(PLOTS)
        for key, png in images.items():
            fig = Figure(figsize=(11.69, 8.27))
            ax = fig.add_axes([0.02, 0.06, 0.96, 0.88])
            ax.imshow(mpimg.imread(io.BytesIO(png), format="png"))
            ax.axis("off")
            fig.text(0.5, 0.02, captions.get(key, key), ha="center")
            pdf.savefig(fig)
    return buf.getvalue()


def write_report(result_dir: Path | str, out: Path | str | None = None, *, pdf: bool = False,
                 measurement: Measurement | None = None, references: list[Reference] = ()) -> list[Path]:
    """Write ``report.html`` (and ``report.pdf``) for a run's output folder. Returns the paths."""
    result_dir = Path(result_dir)
    summary, images, rows = load_result(result_dir)
    out = Path(out) if out else result_dir / "report.html"
    atomic_write_bytes(out, render_html(summary, images, rows, measurement=measurement,
                                        references=references).encode("utf-8"))
    written = [out]
    if pdf:
        p = out.with_suffix(".pdf")
        atomic_write_bytes(p, render_pdf(summary, images, rows, measurement=measurement, references=references))
        written.append(p)
    return written
