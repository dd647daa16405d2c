"""The report as PDF (A4, matplotlib): a summary page (header, Q with its interval and grade, result,
parameters), then the figures two per page and the subsection table. ``records.report`` calls it for
``--pdf``; the rows of text come from ``records.report_content`` as the HTML's do."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib.image as mpimg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from fieldtool.records.history import Measurement, Reference
from fieldtool.records.report_content import (
    COLUMN_NAMES,
    GRADE_COLOURS,
    PLOTS,
    discharge_text,
    fmt_value,
    header_rows,
    parameter_rows,
)


def _pdf_text_page(fig, summary, measurement, references) -> None:
    """Page 1 of the PDF: header, Q with interval and grade, result and parameters."""
    inputs = summary.get("inputs") or {}
    t = discharge_text(summary)
    y = 0.955
    fig.text(0.06, y, f"Discharge measurement — {inputs.get('name', 'measurement')}", fontsize=15, weight="bold")
    y -= 0.035
    for k, v in header_rows(summary, measurement):
        fig.text(0.06, y, k, fontsize=9, color="0.35")
        fig.text(0.24, y, v, fontsize=9, weight="bold")
        y -= 0.018
    y -= 0.015
    fig.text(0.06, y, f"Q = {t['q']}", fontsize=18, weight="bold")
    if t["grade"]:
        fig.text(0.62, y + 0.004, f" {t['grade'].upper()} ", fontsize=12, weight="bold", color="white",
                 bbox={"boxstyle": "round,pad=0.3", "fc": GRADE_COLOURS.get(t["grade"], "0.4"), "lw": 0})
    y -= 0.025
    fig.text(0.06, y, f"95 % interval {t['ci']} ({t['rel']})" if t["ci"] else "no 95 % interval in this result",
             fontsize=10)
    y -= 0.02
    for sev, msg in t["reasons"][:8]:
        fig.text(0.08, y, f"• {sev}: {msg}"[:130], fontsize=8.5)
        y -= 0.016
    if summary.get("discharge_p05_m3s") is not None:
        fig.text(0.06, y, f"spread of single frame pairs (5–95 %): {fmt_value(summary.get('discharge_p05_m3s'), '.3f')} – "
                          f"{fmt_value(summary.get('discharge_p95_m3s'), '.3f')} m³/s over {summary.get('n_pairs', '?')} pairs",
                 fontsize=8, color="0.35")
        y -= 0.02
    y -= 0.01
    level, level_sd = summary.get("water_level_m"), summary.get("water_level_uncertainty_m")
    area, width = summary.get("wetted_area_m2"), summary.get("wetted_width_m")
    res = [("Water level", f"{fmt_value(level, '.3f', 'm')} ± {fmt_value(level_sd, '.3f', 'm')}"),
           ("Wetted area / width", f"{fmt_value(area, '.3f', 'm²')} / {fmt_value(width, '.3f', 'm')}"),
           ("Mean velocity, α", f"{fmt_value(summary.get('mean_velocity_ms'), '.3f', 'm/s')}, α = {fmt_value(summary.get('alpha'), '.2f')}")]
    res += [(f"Reference ({r.method})", f"{fmt_value(r.discharge_m3s, '.3f')} m³/s") for r in references]
    for k, v in res:
        fig.text(0.06, y, k, fontsize=9, color="0.35")
        fig.text(0.30, y, v, fontsize=9)
        y -= 0.017
    y -= 0.012
    fig.text(0.06, y, "Parameters", fontsize=11, weight="bold")
    y -= 0.02
    for a, b, c in parameter_rows(inputs):
        if y < 0.04:
            break
        fig.text(0.06, y, a, fontsize=8, color="0.35")
        fig.text(0.26, y, b, fontsize=8)
        fig.text(0.50, y, c[:70], fontsize=8)
        y -= 0.0155


def render_pdf(summary: dict, images: dict[str, bytes], subsections: list[dict], *,
               measurement: Measurement | None = None, references: Sequence[Reference] = ()) -> bytes:
    """The report as PDF bytes (A4): a summary page, then the figures two per page (matplotlib)."""
    buf = io.BytesIO()
    with PdfPages(buf) as pdf:
        fig = Figure(figsize=(8.27, 11.69))
        _pdf_text_page(fig, summary, measurement, references)
        pdf.savefig(fig)
        captions = dict(PLOTS)
        order = [k for k, _ in PLOTS if k in images] + sorted(k for k in images if k not in captions)
        for first in range(0, len(order), 2):
            fig = Figure(figsize=(8.27, 11.69))
            for slot, key in enumerate(order[first:first + 2]):
                ax = fig.add_axes((0.06, 0.53 - 0.47 * slot, 0.88, 0.42))
                ax.imshow(mpimg.imread(io.BytesIO(images[key]), format="png"))
                ax.axis("off")
                fig.text(0.5, 0.51 - 0.47 * slot, captions.get(key, key), ha="center", fontsize=9)
            pdf.savefig(fig)
        if subsections:
            fig = Figure(figsize=(8.27, 11.69))
            cols = [c for c in COLUMN_NAMES if c in subsections[0]]
            ax = fig.add_axes((0.06, 0.05, 0.88, 0.85))
            ax.axis("off")
            ax.set_title("Subsections", loc="left")
            tab = ax.table(cellText=[[r[c] for c in cols] for r in subsections],
                           colLabels=[COLUMN_NAMES[c] for c in cols], loc="upper center")
            tab.auto_set_font_size(False)
            tab.set_fontsize(7.5)
            pdf.savefig(fig)
    return buf.getvalue()
