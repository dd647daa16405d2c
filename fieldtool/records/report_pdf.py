"""The report as a PDF (A4, matplotlib): everything the HTML report has, in the same order.

Header, Q with its 95 % interval, grade and reasons, the spread of the frame pairs, the uncertainty budget,
the result table (level, area, width, velocity, α, pairs, valid fraction, filled subsections, GCP RMS),
several sections, reference discharges, the warnings, the subsections table (every column, STIV included;
"filled" as yes / no), the parameters, then the figures two per page.

Text flows from page to page (a table or a list longer than a page goes on on the next one). Tables are set
in a monospaced font with each column as wide as its widest cell, and a header wider than its column is
wrapped over two or three lines, so that headers never overlap. The text stays text in the PDF (pdftotext
reads it back).
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Set
from datetime import UTC, datetime

import matplotlib.image as mpimg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from fieldtool import __version__
from fieldtool.records.report_content import (
    COLUMN_NAMES,
    budget_rows,
    discharge_text,
    header_rows,
    parameter_rows,
    result_rows,
    sections_rows,
    standard_rows,
    subsection_cell,
)

A4 = (8.27, 11.69)  # inches
LEFT, RIGHT, TOP, BOTTOM = 0.07, 0.95, 0.955, 0.045  # figure fractions
PT = 1.0 / (A4[1] * 72.0)  # one point as a fraction of the page height
WIDTH_PT = (RIGHT - LEFT) * A4[0] * 72.0
MONO = "DejaVu Sans Mono"
GRADE_COLOURS = {"good": "#1a7f37", "doubtful": "#9a6700", "unusable": "#cf222e"}


class _Flow:
    """A cursor down A4 pages: text, headings, tables and images, a new page when one is full."""

    def __init__(self, pdf: PdfPages):
        self.pdf = pdf
        self.fig: Figure | None = None
        self.y = TOP

    def _page(self) -> None:
        if self.fig is not None:
            self.pdf.savefig(self.fig)
        self.fig = Figure(figsize=A4)
        self.y = TOP

    @property
    def page(self) -> Figure:
        """The page being drawn on (``need`` opens one)."""
        assert self.fig is not None, "need() opens a page before anything is drawn"
        return self.fig

    def need(self, height: float) -> None:
        if self.fig is None or self.y - height < BOTTOM:
            self._page()

    def gap(self, pts: float) -> None:
        self.y -= pts * PT

    def text(self, s: str, size: float = 9.0, indent: float = 0.0, **kw) -> None:
        """A paragraph, wrapped to the page width (about 0.55 em per character)."""
        chars = max(20, int((WIDTH_PT - indent * A4[0] * 72) / (0.55 * size)))
        for line in textwrap.wrap(s, chars, break_long_words=True) or [""]:
            self.need(size * 1.4 * PT)
            self.y -= size * 1.4 * PT
            self.page.text(LEFT + indent, self.y, line, fontsize=size, **kw)

    def heading(self, s: str) -> None:
        self.need(40 * PT)
        self.gap(8)
        self.text(s, size=11.5, weight="bold")
        self.gap(2)

    def table(self, header: list[str], rows: list[list[str]], size: float = 7.5, right: Set[int] = frozenset()) -> None:
        """A table in a monospaced font; the columns of ``right`` are right-aligned."""
        rows = [[str(c) for c in r] for r in rows]
        n = len(header)
        widths = [
            max(
                [len(r[i]) for r in rows if i < len(r)]
                + [len(w) for w in header[i].split()]
                + [-(-len(header[i]) // 3), 1]
            )
            for i in range(n)
        ]  # a header: whole words, 3 lines at most
        max_chars = int(WIDTH_PT / (0.602 * size)) - 2 * (n - 1)
        while sum(widths) > max_chars and max(widths) > 8:  # a very long cell (a path) is cut, never the page
            widths[widths.index(max(widths))] -= 1
        heads = [textwrap.wrap(h, widths[i], break_long_words=False) or [""] for i, h in enumerate(header)]
        depth = max(len(h) for h in heads)

        def line(cells: list[str]) -> str:
            out = []
            for i in range(n):
                c = cells[i] if i < len(cells) else ""
                c = c if len(c) <= widths[i] else c[: widths[i] - 1] + "…"
                out.append(c.rjust(widths[i]) if i in right else c.ljust(widths[i]))
            return "  ".join(out).rstrip()

        lh = size * 1.35 * PT
        head_lines = [line([h[k] if k < len(h) else "" for h in heads]) for k in range(depth)]

        def draw_head() -> None:
            self.need((depth + 2) * lh)
            for hl in head_lines:
                self.y -= lh
                self.page.text(LEFT, self.y, hl, fontsize=size, family=MONO, weight="bold")
            self.y -= 0.35 * lh
            self.page.add_artist(
                Line2D([LEFT, RIGHT], [self.y, self.y], lw=0.5, color="0.4", transform=self.page.transFigure)
            )

        draw_head()
        for r in rows:
            if self.y - lh < BOTTOM:
                self._page()
                draw_head()
            self.y -= lh
            self.page.text(LEFT, self.y, line(r), fontsize=size, family=MONO)
        self.gap(4)

    def pairs(self, rows: list[tuple[str, str]], size: float = 9.0, key_w: float = 0.24) -> None:
        """(label, value) rows in two columns; a long value wraps under itself."""
        chars = max(20, int((RIGHT - LEFT - key_w) * A4[0] * 72 / (0.55 * size)))
        for k, v in rows:
            lines = textwrap.wrap(str(v), chars) or ["–"]
            self.need(len(lines) * size * 1.4 * PT)
            self.y -= size * 1.4 * PT
            self.page.text(LEFT, self.y, str(k), fontsize=size, color="0.35")
            for i, ln in enumerate(lines):
                if i:
                    self.y -= size * 1.4 * PT
                self.page.text(LEFT + key_w, self.y, ln, fontsize=size, weight="bold" if size >= 9 else "normal")

    def close(self) -> None:
        if self.fig is not None:
            self.pdf.savefig(self.fig)
            self.fig = None


def _q_block(flow: _Flow, summary: dict) -> None:
    t = discharge_text(summary)
    flow.need(60 * PT)
    flow.gap(6)
    flow.y -= 18 * PT
    flow.page.text(LEFT, flow.y, f"Q = {t['q']}", fontsize=18, weight="bold")
    if t["grade"]:
        flow.page.text(
            0.62,
            flow.y + 2 * PT,
            f" {t['grade'].upper()} ",
            fontsize=12,
            weight="bold",
            color="white",
            bbox={"boxstyle": "round,pad=0.3", "fc": GRADE_COLOURS.get(t["grade"], "0.4"), "lw": 0},
        )
    flow.gap(4)
    flow.text(
        f"95 % interval {t['ci']} ({t['rel']})"
        if t["ci"]
        else "no 95 % interval in this result (computed by newer fieldtool runs)",
        size=10,
    )
    if t["grade"]:
        if t["reasons"]:
            for sev, msg in t["reasons"]:
                flow.text(f"• {sev}: {msg}", size=8.5, indent=0.02)
        else:
            flow.text("no reason for doubt found", size=8.5, color="0.35")
    else:
        flow.text("no quality grade in this result", size=8.5, color="0.35")
    lo, hi = summary.get("discharge_p05_m3s"), summary.get("discharge_p95_m3s")
    if lo is not None and hi is not None:
        flow.text(
            f"Spread of the discharge of single frame pairs (not an interval of Q): 5–95 % {float(lo):.3f} – "
            f"{float(hi):.3f} m³/s over {summary.get('n_pairs', '?')} frame pairs.",
            size=8,
            color="0.35",
        )


def render_pdf(
    summary: dict,
    images: dict[str, bytes],
    subsections: list[dict],
    *,
    measurement=None,
    references=(),
    plots: tuple = (),
) -> bytes:
    """The report as PDF bytes (A4); ``plots`` = (files key, caption) in report order."""
    inputs = summary.get("inputs") or {}
    q = summary.get("discharge_m3s")
    buf = io.BytesIO()
    with PdfPages(buf) as pdf:
        flow = _Flow(pdf)
        flow.need(1)
        flow.text(f"Discharge measurement — {inputs.get('name') or 'measurement'}", size=15, weight="bold")
        flow.gap(4)
        flow.pairs(header_rows(summary, measurement), size=8.5, key_w=0.16)
        _q_block(flow, summary)
        std = standard_rows(summary)
        if std:  # the hydrologists' standard uncertainty beside ours, as in the HTML
            flow.heading("Uncertainty by method (2σ)")
            flow.table(["method", "95 % interval", "relative", "USGS rating"], [list(r) for r in std])
        budget = budget_rows(summary)
        if budget:
            flow.heading("Uncertainty budget")
            flow.table(
                ["uncertainty source", "share of variance", "u (m³/s)"], [list(r) for r in budget], size=8, right={1, 2}
            )
        flow.heading("Result")
        flow.pairs(result_rows(summary), size=9, key_w=0.34)
        secs = sections_rows(summary)
        if secs:
            flow.heading("Sections")
            flow.table(
                ["section", "Q (m³/s)", "95 % interval (m³/s)", "grade", "wetted width (m)", "mean velocity (m/s)"],
                [list(r) for r in secs],
                right={1, 4, 5},
            )
        if references:
            flow.heading("Reference discharges")
            rows = []
            for r in references:
                err = 100.0 * (q - r.discharge_m3s) / r.discharge_m3s if q is not None and r.discharge_m3s else None
                rows.append(
                    [
                        str(r.method),
                        f"{r.discharge_m3s:.4f}",
                        "–" if r.uncertainty_m3s is None else f"{r.uncertainty_m3s:.4f}",
                        "–" if err is None else f"{err:+.2f}",
                        str(r.note or ""),
                    ]
                )
            flow.table(["method", "Q ref (m³/s)", "± (m³/s)", "LSPIV − ref (%)", "note"], rows, right={1, 2, 3})
        warnings = summary.get("warnings") or []
        if warnings:
            flow.heading("Warnings")
            for w in warnings:
                flow.text(f"• {w}", size=8.5, color="#9a6700")
        if subsections:
            cols: list[str] = [c for c in COLUMN_NAMES if c in subsections[0]] + [
                c for c in subsections[0] if c not in COLUMN_NAMES
            ]
            flow.heading("Subsections")
            flow.table(
                [COLUMN_NAMES.get(c, c) for c in cols],
                [[subsection_cell(c, r.get(c)) for c in cols] for r in subsections],
                right={i for i, c in enumerate(cols) if c != "velocity_filled"},
            )
        flow.heading("Parameters")
        flow.table(["step", "parameter", "value"], [list(r) for r in parameter_rows(inputs)], size=7.5)
        if measurement is not None and getattr(measurement, "input_hash", None):
            flow.text(
                f"history id {measurement.id}; input hash (SHA-256 of parameters and input files): "
                f"{measurement.input_hash}",
                size=7.5,
                color="0.35",
            )
        now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        flow.text(
            f"report written {now} by fieldtool {__version__}; the run used fieldtool "
            f"{summary.get('fieldtool_version', '?')}. Every value of the run: result.json.",
            size=7.5,
            color="0.35",
        )
        flow.close()

        captions = dict(plots)
        order = [k for k, _ in plots if k in images] + sorted(k for k in images if k not in captions)
        for first in range(0, len(order), 2):
            fig = Figure(figsize=A4)
            for slot, key in enumerate(order[first : first + 2]):
                ax = fig.add_axes((0.06, 0.53 - 0.47 * slot, 0.88, 0.42))
                ax.imshow(mpimg.imread(io.BytesIO(images[key]), format="png"))
                ax.axis("off")
                fig.text(0.5, 0.51 - 0.47 * slot, captions.get(key, key), ha="center", fontsize=9)
            pdf.savefig(fig)
    return buf.getvalue()
