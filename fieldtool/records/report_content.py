"""What the report says, as plain rows of text, shared by the HTML and the PDF.

- :func:`header_rows`: site, station, operator, video file, recording time, duration, size, rate;
- :func:`discharge_text`: Q with its 95 % interval (``discharge_ci95_m3s`` / ``uncertainty``) and
  the quality grade with its reasons (``quality``), or what is missing when the run lacks them;
- :func:`standard_rows`: the ISO 748 and IVE intervals (``uncertainty_standard``) beside the Monte Carlo one;
- :func:`parameter_rows`: the measurement's parameters in words and units. Internal keys (picked
  pixel lists, the TUI's last step, the live-stream settings) are not shown: the input hash and
  ``result.json`` keep the exact values.
"""

from __future__ import annotations

import html
from pathlib import Path

# plots of result.json "files", in report order, with captions
PLOTS = (
    ("profile_png", "Surface velocity along the section, with the spread of the frame-pair fields"),
    ("vectors_png", "Surface velocity vectors on the first frame"),
    ("rectified_png", "Rectified image with the velocity field (world metres)"),
    ("section_png", "Cross-section, water level and subsection velocities / discharges"),
    ("gcp_png", "Ground control points with the taped distances and their residuals"),
    ("water_level_png", "Water level determination"),
    ("stabilization_png", "Stabilisation"),
)
GRADE_COLOURS = {"good": "#1a7f37", "doubtful": "#9a6700", "unusable": "#cf222e"}


# columns of the subsection table, with their headings
def fmt_value(v, fmt: str = ".4f", unit: str = "") -> str:
    """``v`` formatted with ``fmt`` and its unit; "–" for None, the escaped text of what is not a number."""
    if v is None:
        return "–"
    try:
        return f"{float(v):{fmt}}{(' ' + unit) if unit else ''}"
    except (TypeError, ValueError):
        return html.escape(str(v))


def _num(v, fmt: str = ".3f", unit: str = "") -> str:
    try:
        return f"{float(v):{fmt}}" + (f" {unit}" if unit else "")
    except (TypeError, ValueError):
        return "–"


def header_rows(summary: dict, measurement=None) -> list[tuple[str, str]]:
    """(label, value) rows of the report's header."""
    inputs = summary.get("inputs") or {}
    video = summary.get("video") or {}
    site = (measurement.site if measurement is not None and measurement.site else None) or inputs.get("site") or "–"
    when, source = video.get("recorded_utc"), video.get("recorded_source")
    if measurement is not None and measurement.video_time:
        when, source = measurement.video_time, measurement.video_time_source
    if when:
        recorded = when.replace("T", " ").replace("Z", " UTC") + (
            " (from the video container)" if source == "container" else f" ({source}: the container gave no date)"
        )
    else:
        recorded = "unknown"
    vpath = video.get("file") or Path(str((inputs.get("video") or {}).get("path", ""))).name or "–"
    rows = [
        ("Site", str(site)),
        ("Station", inputs.get("station") or "–"),
        ("Operator", inputs.get("operator") or "–"),
        ("Video file", vpath),
        ("Recorded", recorded),
    ]
    if video:
        dur = _num(video.get("duration_s"), ".2f", "s")
        used = f"{_num(video.get('start_s'), '.2f')} – " + (
            _num(video.get("end_s"), ".2f", "s") if video.get("end_s") is not None else "end"
        )
        rows += [
            ("Duration", f"{dur} (analysed {used})"),
            ("Resolution", f"{video.get('width_px', '?')} × {video.get('height_px', '?')} px"),
            (
                "Frame rate",
                _num(video.get("fps"), ".4g", "frames/s")
                + (f", {video.get('n_frames')} frames" if video.get("n_frames") else ""),
            ),
        ]
    return rows


def interval(summary: dict) -> tuple[float, float] | None:
    """The 95 % interval of Q (m³/s) from the quality helper's keys, or None when the run has none."""
    ci = summary.get("discharge_ci95_m3s") or (summary.get("uncertainty") or {}).get("ci95_m3s")
    if ci is None:
        return None
    try:
        lo, hi = (float(v) for v in ci)
    except (TypeError, ValueError):
        return None
    return lo, hi


def discharge_text(summary: dict) -> dict:
    """Q, its interval, the relative half-width, the grade and the reasons, as text."""
    q = summary.get("discharge_m3s")
    ci = interval(summary)
    out: dict = {"q": _num(q, ".3f", "m³/s"), "ci": None, "rel": None, "grade": None, "reasons": []}
    if ci is not None:
        out["ci"] = f"{ci[0]:.3f} – {ci[1]:.3f} m³/s"
        if q:
            out["rel"] = f"± {100 * (ci[1] - ci[0]) / 2 / abs(float(q)):.1f} %"
    qual = summary.get("quality")
    if isinstance(qual, dict) and qual.get("grade"):
        out["grade"] = str(qual["grade"])
        for r in qual.get("reasons") or []:
            if not isinstance(r, dict):
                continue
            extra = ""
            if r.get("value") is not None and r.get("threshold") is not None:
                extra = f" (value {r['value']:.3g}, limit {r['threshold']:.3g})"
            out["reasons"].append((str(r.get("severity", "")), f"{r.get('message', r.get('code', ''))}{extra}"))
    return out


def budget_rows(summary: dict) -> list[tuple[str, str, str]]:
    """(source, share, u) rows of the uncertainty budget, when the run has one."""
    names = {
        "water_level": "water level",
        "gcp_pixels": "GCP picks (pixels)",
        "gcp_distances": "GCP distances",
        "velocity_index": "velocity index α",
        "velocity_sampling": "velocity sampling (frame pairs)",
        "filled_subsections": "filled subsections",
        "cross_section": "cross-section survey",
    }
    rows = []
    for b in (summary.get("uncertainty") or {}).get("budget") or []:
        if isinstance(b, dict):
            rows.append(
                (
                    names.get(str(b.get("source")), str(b.get("source"))),
                    _num(100 * float(b.get("share") or 0), ".0f", "%"),
                    _num(b.get("u_m3s"), ".3f", "m³/s"),
                )
            )
    return rows


STANDARD_NAMES = (("iso748", "ISO 748:2007 (velocity-area)"), ("ive", "IVE (Cohn et al. 2013)"))


def standard_rows(summary: dict) -> list[tuple[str, str, str, str]]:
    """(method, 95 % interval, ± relative, USGS rating) of the Monte Carlo and the standard methods (2σ);
    empty when the result has no ``uncertainty_standard`` (older runs)."""
    std = summary.get("uncertainty_standard")
    if not isinstance(std, dict):
        return []
    rows = []
    ci = interval(summary)
    q = summary.get("discharge_m3s")
    if ci is not None and q:
        rel = (ci[1] - ci[0]) / 2 / abs(float(q))
        rows.append(("Monte Carlo (fieldtool)", f"{ci[0]:.3f} – {ci[1]:.3f} m³/s", f"± {100 * rel:.1f} %", "–"))
    for key, name in STANDARD_NAMES:
        b = std.get(key)
        if not isinstance(b, dict) or not b.get("ci95_m3s"):
            continue
        lo, hi = b["ci95_m3s"]
        rows.append(
            (name, f"{lo:.3f} – {hi:.3f} m³/s", f"± {100 * float(b['u95_rel']):.1f} %", str(b.get("rating") or "–"))
        )
    return rows


def parameter_rows(inputs: dict) -> list[tuple[str, str, str]]:
    """(group, parameter, value) rows in words and units."""
    g = lambda t: inputs.get(t) or {}  # noqa: E731
    rows: list[tuple[str, str, str]] = []
    v = g("video")
    rows.append(
        (
            "Video",
            "Time range",
            f"{_num(v.get('start_s', 0), '.2f')} – "
            + (_num(v["end_s"], ".2f", "s") if v.get("end_s") is not None else "end of clip"),
        )
    )
    rows.append(("Video", "Frames used", "every frame" if v.get("step", 1) == 1 else f"every {v['step']}th frame"))
    c = g("cross_section")
    if c.get("shape"):
        dims = ", ".join(
            f"{k.removesuffix('_m').replace('_', ' ')} {_num(c[k], '.2f', 'm')}"
            for k in ("top_width_m", "bottom_width_m", "depth_m")
            if c.get(k) is not None
        )
        rows.append(("Cross-section", "Shape", f"{c['shape']}" + (f" ({dims})" if dims else "")))
    else:
        rows.append(("Cross-section", "Survey file", Path(str(c.get("path", "–"))).name or "–"))
    cal = g("calibration")
    rows.append(("Lens", "Calibration", Path(cal["path"]).name if cal.get("path") else "none (lens not corrected)"))
    st = g("stabilize")
    rows.append(
        (
            "Stabilisation",
            "Image stabilisation",
            f"on ({st.get('model', 'homography')})" if st.get("enabled") else "off",
        )
    )
    o = g("ortho")
    method = {
        "distances": "4 GCPs and 6 taped distances",
        "world": "GCPs with surveyed coordinates",
        "pose": "camera pose from 3-D GCPs",
        "two_points": "2 GCPs and their distance (nadir)",
        "none": "scale from the wetted width (nadir)",
    }
    rows.append(("Orthorectification", "Method", method.get(o.get("method", "distances"), str(o.get("method")))))
    if o.get("distances_m") and o.get("method", "distances") == "distances":
        rows.append(("Orthorectification", "Distances L1–L6", ", ".join(f"{d:.3f}" for d in o["distances_m"]) + " m"))
    if o.get("crs_epsg"):
        rows.append(("Orthorectification", "Coordinate system", f"EPSG:{o['crs_epsg']}"))
    w = g("water_level")
    wm = w.get("method", "value")
    wl = {
        "value": "typed value",
        "width": "from the wetted width",
        "dem": "from a bank DEM (adapted Hellebaut)",
        "angle_height": "two images at different heights",
        "image": "water edges picked on the frame",
        "waterline": "water edges found in the clip",
    }
    rows.append(("Water level", "Method", wl.get(wm, wm)))
    if wm == "value" and w.get("value_m") is not None:
        rows.append(
            (
                "Water level",
                "Level",
                _num(w["value_m"], ".3f", "m")
                + (f" ± {_num(w['uncertainty_m'], '.3f', 'm')}" if w.get("uncertainty_m") is not None else ""),
            )
        )
    if wm == "width" and w.get("width_m") is not None:
        rows.append(("Water level", "Wetted width", _num(w["width_m"], ".3f", "m")))
    r = g("roi")
    rows.append(("Region", "Region of interest", "set" if r.get("rect_px") else "whole frame"))
    if r.get("masks_px"):
        rows.append(("Region", "Masked areas", str(len(r["masks_px"]))))
    filters = inputs.get("filters") or []
    rows.append(
        (
            "Image filters",
            "Filters (in order)",
            ", ".join(str(f.get("name", "?")) for f in filters if isinstance(f, dict)) or "none",
        )
    )
    p = g("piv")
    rows += [
        ("PIV", "Engine", str(p.get("engine", "fieldtool"))),
        ("PIV", "Interrogation window", f"{p.get('window_px', 32)} px, overlap {p.get('overlap_px', 16)} px"),
        ("PIV", "Search area", f"{p['search_px']} px" if p.get("search_px") else "= window"),
        ("PIV", "Passes", str(p.get("passes", 2))),
        ("PIV", "Averaging", str(p.get("averaging", "ensemble"))),
        ("PIV", "Minimum peak ratio", _num(p.get("snr_min", 1.3), ".2f")),
    ]
    if p.get("max_velocity_ms") is not None:
        rows.append(("PIV", "Maximum velocity", _num(p["max_velocity_ms"], ".2f", "m/s")))
    s = g("section")
    rows.append(("Discharge", "Subsections", str(s.get("n_sub", 15))))
    rows.append(
        (
            "Discharge",
            "Velocity index α",
            _num(s["alpha"], ".2f") if s.get("alpha") is not None else "default (0.8 below 2 m mean depth, else 0.9)",
        )
    )
    if s.get("station_offset_m") is not None:
        rows.append(("Discharge", "Station of the left point", _num(s["station_offset_m"], ".2f", "m")))
    return rows


def velocities_used(stiv_block: dict | None) -> str:
    """Whose velocities a result's discharge is of: piv | stiv | combined, from its ``"stiv"`` block. A result
    written before ``velocity_source_used`` existed (stop 51 and earlier) had no "auto": its key was the source."""
    st = stiv_block or {}
    return st.get("velocity_source_used", st.get("velocity_source", "piv"))


def velocities_text(summary: dict, q_unit: str = "m³/s", short: bool = False) -> str:
    """Which velocities the discharge is of (``stiv.velocity_source_used``), with PIV's and STIV's own discharges
    (in ``q_unit``, its name: the terminal's is "m3/s") beside where the two were combined; ``short``: the
    source's name alone ("PIV", "STIV", "PIV+STIV"), for a line that has no room."""
    st = summary.get("stiv") or {}
    used = velocities_used(st)
    text = {"piv": "PIV", "stiv": "STIV", "combined": "PIV and STIV combined per subsection"}[used]
    if short:
        return {"combined": "PIV+STIV"}.get(used, text)
    if used == "combined":
        text += (
            f" (PIV alone {_num(st.get('discharge_piv_m3s'), '.3f', q_unit)}, STIV alone "
            f"{_num(st.get('discharge_m3s'), '.3f', q_unit)})"
        )
    elif used == "piv" and st.get("velocity_source") == "auto" and st.get("disagreement_reason"):
        text += " (STIV disagrees: not combined)"
    return text


def result_rows(summary: dict) -> list[tuple[str, str]]:
    """(label, value) rows of the report's result table (HTML and PDF): level, area, width, velocity, α,
    section length, frame pairs, valid fraction, filled subsections, GCP residual."""
    res = summary.get("ortho_residual_m")
    alpha = _num(summary.get("alpha"), ".2f")
    return [
        (
            "Water level",
            f"{_num(summary.get('water_level_m'), '.3f', 'm')} ± "
            f"{_num(summary.get('water_level_uncertainty_m'), '.3f', 'm')}",
        ),
        ("Wetted area", _num(summary.get("wetted_area_m2"), ".3f", "m²")),
        ("Wetted width", _num(summary.get("wetted_width_m"), ".3f", "m")),
        ("Mean velocity", _num(summary.get("mean_velocity_ms"), ".3f", "m/s")),
        ("Surface velocities", velocities_text(summary)),
        ("Velocity index α", alpha + (" (default for the mean depth)" if summary.get("alpha_default") else " (given)")),
        ("Section length", _num(summary.get("section_length_m"), ".3f", "m")),
        ("Frame pairs", str(summary.get("n_pairs", "–"))),
        ("Mean valid vector fraction", _num(summary.get("valid_fraction_mean"), ".2f")),
        ("Subsections with filled velocity", str(summary.get("subsections_filled", "–"))),
        ("GCP fit residual (RMS)", _num(1000 * res, ".1f", "mm") if isinstance(res, (int, float)) else "–"),
    ]


# subsections.csv columns as the report names them (a column not listed keeps its name)
COLUMN_NAMES = {
    "subsection": "#",
    "station_from_m": "from (m)",
    "station_to_m": "to (m)",
    "area_m2": "area (m²)",
    "mean_depth_m": "mean depth (m)",
    "surface_velocity_ms": "surface velocity (m/s)",
    "velocity_filled": "filled",
    "discharge_m3s": "Q (m³/s)",
    "stiv_velocity_ms": "STIV velocity (m/s)",
}


def subsection_cell(column: str, value) -> str:
    """A subsections.csv cell as the report shows it: "filled" as yes / no, an empty STIV cell as "–"."""
    text = "" if value is None else str(value).strip()
    if column == "velocity_filled":
        return {"1": "yes", "0": "no", "true": "yes", "false": "no"}.get(text.lower(), text or "–")
    return text or "–"


def sections_rows(summary: dict) -> list[tuple[str, ...]]:
    """(name, Q, 95 % interval, grade, wetted width, mean velocity) per section of a several-sections run,
    then the mean / std / CV row; [] when the run has one section."""
    rows: list[tuple[str, ...]] = []
    for e in summary.get("sections") or []:
        if "error" in e:
            rows.append((str(e.get("name")), str(e["error"]), "", "", "", ""))
            continue
        ci = e.get("discharge_ci95_m3s")
        rows.append(
            (
                str(e.get("name")),
                _num(e.get("discharge_m3s"), ".4f"),
                f"{_num(ci[0], '.4f')} – {_num(ci[1], '.4f')}" if ci else "–",
                str(e.get("grade") or "–"),
                _num(e.get("wetted_width_m"), ".3f"),
                _num(e.get("mean_velocity_ms"), ".3f"),
            )
        )
    sm = summary.get("sections_summary") or {}
    if rows and sm:
        cv = sm.get("cv")
        rows.append(
            (
                f"mean of {sm.get('n')}",
                _num(sm.get("mean_m3s"), ".4f"),
                f"std {_num(sm.get('std_m3s'), '.4f')} m³/s, "
                f"CV {_num(100 * cv if cv is not None else None, '.1f', '%')}",
                "",
                "",
                "",
            )
        )
    return rows
