"""`fieldtool site ...`, `fieldtool history ...`, `fieldtool report` and `fieldtool batch`.

Handlers return an exit code; FieldToolError is printed by ``cli.main`` (exit 2).
`fieldtool batch` exits 1 when some items failed (the others are done and recorded).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from fieldtool.errors import ParameterError
from fieldtool.project.model import atomic_write_bytes
from fieldtool.records.history import (
    History,
    Measurement,
    Reference,
    export_csv,
    input_hash,
    parse_time,
    resolve_db_path,
    video_datetime,
)
from fieldtool.records.report import load_result, write_report
from fieldtool.records.sites import (
    SITE_FILE,
    create_site,
    describe,
    list_sites,
    load_site,
    load_site_project,
    new_measurement,
    sites_dir,
)


def _add_db(p: argparse.ArgumentParser, under_history: bool = False) -> None:
    # under `history`, a subcommand's --db must not reset one given before it (`history --db X list`)
    kw: dict[str, Any] = {"default": argparse.SUPPRESS} if under_history else {}
    p.add_argument(
        "--db", help="history database (default: $FIELDTOOL_DB, else history.sqlite in the user data folder)", **kw
    )


def _add_sites(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sites", help="sites folder (default: $FIELDTOOL_SITES, else sites/ in the user data folder)")


def _add_filters(p: argparse.ArgumentParser) -> None:
    p.add_argument("--site", help="only this site")
    p.add_argument("--since", help="videos taken on or after this date (2024-05-01 or 2024-05-01T10:00, UTC)")
    p.add_argument("--until", help="videos taken on or before this date (a date alone means its end)")


def _filters(args) -> dict:
    until = args.until
    if until and len(until.strip()) == 10:  # a bare date: the whole day
        until = until.strip() + "T23:59:59"
    return {
        "site": args.site,
        "since": parse_time(args.since, "--since") if args.since else None,
        "until": parse_time(until, "--until") if until else None,
    }


def _open_history(args, create: bool):
    return History(resolve_db_path(args.db), create=create)


def _history_or_none(args):
    """The history for reading, or None when there is none yet (nothing recorded)."""
    path = resolve_db_path(args.db)
    if not path.exists():
        print(
            f"no history yet ({path} does not exist); runs are recorded by `fieldtool batch`, "
            "`fieldtool site new-measurement --run` and `fieldtool history add`",
            file=sys.stderr,
        )
        return None
    return _open_history(args, create=False)


def _batch():
    """records.batch, lazy: it runs measurements (the pipeline: numpy, OpenCV, SciPy, about 0.5 s to import),
    which `fieldtool site new-measurement --run` and `fieldtool batch` need and the other commands do not."""
    from fieldtool.records import batch

    return batch


def _fmt(v, spec=".4f") -> str:
    return "-" if v is None else format(v, spec)


# ---------------------------------------------------------------------------------------------
# site


def cmd_site_create(args) -> int:
    project = load_site_project(args.from_project)
    site = create_site(
        args.name,
        project,
        sites_dir(args.sites),
        description=args.description or "",
        force=args.force,
        source=str(Path(args.from_project).resolve()),
    )
    print(f"site {site.name!r} written to {site.folder}")
    print(f"next visit: fieldtool site new-measurement {site.name} --video VIDEO --level LEVEL_M --run")
    return 0


def cmd_site_list(args) -> int:
    root = sites_dir(args.sites)
    broken: list = []
    sites = list_sites(root, broken)
    if not sites and not broken:
        print(f"no sites in {root}; create one with `fieldtool site create NAME --from PROJECT.toml`")
        return 0
    w = max(len(s.name) for s in [*sites, *broken])
    for s in sites:
        print(f"{s.name:<{w}}  {s.updated_at or s.created_at:<20}  {s.description}")
    for b in broken:
        print(f"{b.name!r:<{w}}  BROKEN                {b.reason}")
    return 0


def cmd_site_show(args) -> int:
    site = load_site(args.name, sites_dir(args.sites))
    if args.toml:
        sys.stdout.write((site.folder / SITE_FILE).read_text(encoding="utf-8"))
        return 0
    print("\n".join(describe(site)))
    return 0


def cmd_site_new_measurement(args) -> int:
    site = load_site(args.name, sites_dir(args.sites))
    video = Path(args.video)
    out = Path(args.out) if args.out else Path.cwd() / f"{site.name}_{video.stem}"
    proj = new_measurement(site, video, args.level, out, level_uncertainty_m=args.level_uncertainty, force=args.force)
    print(f"wrote {proj}")
    if not args.run:
        print(f"run it with: fieldtool run {proj}   (or add --run to compute and record it now)")
        return 0
    batch = _batch()
    item = batch.BatchItem(label=video.name, project_path=str(proj), out_dir=str(out / "results"), site=site.name)
    with _open_history(args, create=True) as hist:
        res = batch.run_batch([item], history=hist, workers=1, reports=True).results[0]
    if not res.ok:
        raise ParameterError(f"{video.name}: {res.error}")
    s = res.summary
    print(
        f"discharge     {s['discharge_m3s']:.4f} m3/s  (pairs 5-95 %: {_fmt(s.get('discharge_p05_m3s'))} - "
        f"{_fmt(s.get('discharge_p95_m3s'))})"
    )
    print(f"water level   {s['water_level_m']:.3f} m   mean velocity {s['mean_velocity_ms']:.4f} m/s")
    for w in s.get("warnings", []):
        print(f"warning: {w}")
    print(f"recorded as history id {res.history_id}; report {Path(item.out_dir) / 'report.html'}")
    return 0


# ---------------------------------------------------------------------------------------------
# history


def _relative_widths(m) -> str:
    """'MC/ISO/IVE' relative half-widths of the 95 % intervals in percent ('-' where a row has none)."""
    std = m.uncertainty_standard
    mc = (
        None
        if m.discharge_ci95_lo_m3s is None or m.discharge_ci95_hi_m3s is None or not m.discharge_m3s
        else 50 * (m.discharge_ci95_hi_m3s - m.discharge_ci95_lo_m3s) / abs(m.discharge_m3s)
    )
    vals = [mc] + [
        None if (std.get(k) or {}).get("u95_rel") is None else 100 * std[k]["u95_rel"] for k in ("iso748", "ive")
    ]
    return "/".join("-" if v is None else f"{v:.1f}" for v in vals)


def cmd_history_list(args) -> int:
    hist = _history_or_none(args)
    if hist is None:
        return 0
    with hist:
        rows = hist.query(**_filters(args), limit=args.limit, newest_first=True)
        nref: dict[int, int] = {}
        for r in hist.references():
            nref[r.measurement_id] = nref.get(r.measurement_id, 0) + 1
    if not rows:
        print("no measurements match")
        return 0
    print(
        f"{'id':>5}  {'site':<14} {'video time (UTC)':<20} {'level m':>8} {'Q m3/s':>9} {'5-95 % m3/s':>17} "
        f"{'v m/s':>7} {'alpha':>5} {'grade':<9} {'MC/ISO/IVE ±%':>15} {'refs':>4}  output"
    )
    for m in rows:
        spread = f"{_fmt(m.discharge_p05_m3s)}-{_fmt(m.discharge_p95_m3s)}"
        print(
            f"{m.id:>5}  {(m.site or '-')[:14]:<14} {(m.video_time or '-'):<20} {_fmt(m.water_level_m, '.3f'):>8} "
            f"{_fmt(m.discharge_m3s):>9} {spread:>17} {_fmt(m.mean_velocity_ms, '.3f'):>7} "
            f"{_fmt(m.alpha, '.2f'):>5} {(m.grade or '-'):<9} {_relative_widths(m):>15} {nref.get(m.id, 0):>4}  "
            f"{m.output_dir}"
        )
    return 0


def cmd_history_show(args) -> int:
    with _open_history(args, create=False) as hist:
        m = hist.get(args.id)
        refs = hist.references(m.id)
    for k, v in m.__dict__.items():
        if k != "parameters_json":
            print(f"{k:<20} {v}")
    for r in refs:
        print(
            f"reference {r.id:<10} {r.discharge_m3s:.4f} m3/s by {r.method}"
            + (f" ± {r.uncertainty_m3s}" if r.uncertainty_m3s is not None else "")
            + (f"  {r.note}" if r.note else "")
        )
    if args.parameters:
        print(m.parameters_json)
    return 0


def cmd_history_export(args) -> int:
    with _open_history(args, create=False) as hist:
        text = export_csv(hist, hist.query(**_filters(args)))
    if args.file == "-":
        sys.stdout.write(text)
    else:
        atomic_write_bytes(args.file, text.encode("utf-8"))
        print(f"wrote {args.file} ({text.count(chr(10)) - 1} measurements)")
    return 0


def cmd_history_add(args) -> int:
    result_dir = Path(args.result_dir)
    summary, _, _ = load_result(result_dir)
    inputs = summary.get("inputs") or {}
    root = Path(args.project).resolve().parent if args.project else result_dir.resolve().parent
    vrel = (inputs.get("video") or {}).get("path", "")
    video = (root / vrel) if vrel and not Path(vrel).is_absolute() else Path(vrel) if vrel else None
    vt = video_datetime(video) if video is not None else (None, None)
    if video is not None and vt[0] is None:
        print(
            f"warning: video {video} not found beside {root}; no video time or input hash (give --project)",
            file=sys.stderr,
        )
    h = input_hash(json.loads(json.dumps(inputs)), root) if vt[0] is not None else ""
    with _open_history(args, create=True) as hist:
        mid = hist.record_summary(
            summary,
            site=args.site or "",
            output_dir=result_dir.resolve(),
            video_path=str(video or ""),
            video_time=vt,
            input_hash=h,
        )
    print(f"recorded as history id {mid}")
    return 0


def cmd_history_reference(args) -> int:
    with _open_history(args, create=False) as hist:
        rid = hist.add_reference(args.id, args.discharge, args.method, args.uncertainty, args.note or "")
        m = hist.get(args.id)
    err = 100.0 * (m.discharge_m3s - args.discharge) / args.discharge if m.discharge_m3s is not None else None
    print(
        f"reference {rid} attached to measurement {args.id}"
        + (f": LSPIV {m.discharge_m3s:.4f} m3/s is {err:+.2f} % from it" if err is not None else "")
    )
    return 0


def cmd_history_delete(args) -> int:
    with _open_history(args, create=False) as hist:
        hist.delete_measurement(args.id)
    print(f"measurement {args.id} deleted (with its references); its output folder was left as it is")
    return 0


def cmd_history_stations(args) -> int:
    """`fieldtool history stations`: what each fixed-camera station measured, has pending and failed."""
    hist = _history_or_none(args)
    if hist is None:
        return 0
    with hist:
        rows = hist.station_counts(args.site)
    if not rows:
        print("no station has measured into this history yet (fieldtool station SITE --incoming DIR)")
        return 0
    print(f"{'site':<16} {'done':>5} {'pending':>8} {'failed':>7}  {'last update (UTC)':<20} folder")
    for site, incoming, c, last in rows:
        pending = c.get("pending", 0) + c.get("running", 0)
        print(f"{site:<16} {c.get('done', 0):>5} {pending:>8} {c.get('failed', 0):>7}  {last[:19]:<20} {incoming}")
    print("details and retries: fieldtool station status|retry SITE --incoming FOLDER")
    return 0


def cmd_history_stats(args) -> int:
    hist = _history_or_none(args)
    if hist is None:
        return 0
    with hist:
        stats = hist.error_stats(args.site)
    if not stats:
        print(
            "no measurement has a reference discharge yet; attach one with "
            "`fieldtool history reference ID Q --method adcp`"
        )
        return 0
    print("LSPIV against reference discharges, error = (Q_lspiv - Q_ref) / Q_ref")
    print(
        f"{'site':<14} {'reference':<13} {'n':>3} {'bias %':>8} {'mean |e| %':>10} {'rmse %':>8} {'max |e| %':>9} "
        f"{'rmse m3/s':>10}"
    )
    for s in stats:
        print(
            f"{(s.site or '-')[:14]:<14} {s.method:<13} {s.n:>3} {s.bias_percent:>+8.2f} {s.mean_abs_percent:>10.2f} "
            f"{s.rmse_percent:>8.2f} {s.max_abs_percent:>9.2f} {s.rmse_m3s:>10.4f}"
        )
    return 0


def cmd_history_rating(args) -> int:
    from fieldtool.records import rating  # lazy: scipy.optimize and matplotlib (0.5-1 s) only for the rating curve

    with _open_history(args, create=False) as hist:
        rows = [m for m in hist.query(site=args.site) if m.discharge_m3s is not None and m.water_level_m is not None]
        pairs = hist.reference_pairs(args.site)
    if not rows:
        raise ParameterError(f"site {args.site!r}: no measurements in the history (see `fieldtool history list`)")
    h = [m.water_level_m for m in rows]
    q = [m.discharge_m3s for m in rows]
    rh = [m.water_level_m for m, _ in pairs if m.water_level_m is not None]
    rq = [r.discharge_m3s for m, r in pairs if m.water_level_m is not None]
    fh, fq = (rh, rq) if args.fit_to == "reference" else (h, q)
    curve = rating.fit_rating(fh, fq, h0=args.h0)
    out = Path(args.out) if args.out else Path.cwd() / f"rating_{args.site}.png"
    rating.plot_rating(
        out,
        curve,
        h,
        q,
        ref_h=rh,
        ref_q=rq,
        site=args.site,
        q_low=[m.discharge_p05_m3s if m.discharge_p05_m3s is not None else float("nan") for m in rows],
        q_high=[m.discharge_p95_m3s if m.discharge_p95_m3s is not None else float("nan") for m in rows],
    )
    print(f"fitted to the {'reference' if args.fit_to == 'reference' else 'LSPIV'} discharges: {curve.describe()}")
    print(f"plot: {out}")
    return 0


# ---------------------------------------------------------------------------------------------
# report


def cmd_report(args) -> int:
    if (args.result_dir is None) == (args.id is None):
        raise ParameterError("give a run's output folder, or --id N of a measurement in the history")
    m: Measurement | None = None
    refs: list[Reference] = []
    db = resolve_db_path(args.db)
    if args.id is not None or db.exists():
        with _open_history(args, create=False) as hist:
            if args.id is not None:
                m = hist.get(args.id)
            else:
                found = hist.query(output_dir=str(Path(args.result_dir).resolve()), newest_first=True, limit=1)
                m = found[0] if found else None
            refs = hist.references(m.id) if m is not None else []
    if args.result_dir:
        result_dir = Path(args.result_dir)
    else:
        assert m is not None  # --id N: hist.get found it (it raises for an unknown id)
        result_dir = Path(m.output_dir)
    written = write_report(result_dir, args.out, pdf=args.pdf, measurement=m, references=refs)
    for p in written:
        print(f"wrote {p}")
    return 0


# ---------------------------------------------------------------------------------------------
# batch


def cmd_batch(args) -> int:
    batch = _batch()
    if args.videos:
        if not args.site:
            raise ParameterError(
                "--videos needs --site NAME: the site whose cross-section, GCPs and parameters the videos share"
            )
        if args.projects or args.list:
            raise ParameterError("give either --videos (a folder of videos of one site) or project files, not both")
        if args.levels is None and args.level is None:
            raise ParameterError("--videos needs the water levels: --levels CSV (video,water_level_m) or --level M")

        site = load_site(args.site, sites_dir(args.sites))
        out = Path(args.out) if args.out else Path(args.videos) / "fieldtool_out"
        items = batch.plan_site_folder(
            site,
            args.videos,
            out,
            levels=batch.read_levels(args.levels) if args.levels else None,
            level_m=args.level,
            level_uncertainty_m=args.level_uncertainty,
        )
    else:
        paths = list(args.projects or [])
        if args.list:
            paths += batch.read_list(args.list)
        if not paths:
            raise ParameterError("nothing to run: give project files, --list FILE, or --site NAME --videos FOLDER")
        items = batch.plan_projects(paths, out_root=args.out, site=args.site or "")

    def on_done(r, done, total):
        if r.ok:
            what = "already in the history" if r.skipped else f"{r.seconds:.1f} s"
            print(
                f"[{done}/{total}] ok      {r.item.label}: Q = {_fmt(r.summary.get('discharge_m3s'))} m3/s ({what})",
                file=sys.stderr,
                flush=True,
            )
        else:
            print(f"[{done}/{total}] FAILED  {r.item.label}: {r.error}", file=sys.stderr, flush=True)

    hist = None if args.no_history else _open_history(args, create=True)
    try:
        res = batch.run_batch(
            items,
            history=hist,
            workers=args.workers,
            scheduler=args.scheduler,
            skip_existing=args.skip_existing,
            reports=args.report,
            on_done=on_done,
        )
    finally:
        if hist is not None:
            hist.close()
    print(f"{len(res.succeeded)} of {len(res.results)} done in {res.wall_s:.1f} s ({res.executor})")
    for r in res.results:
        if r.ok:
            hid = f"history {r.history_id}" if r.history_id else "not recorded"
            print(
                f"  ok      {r.item.label}: Q = {_fmt(r.summary.get('discharge_m3s'))} m3/s, level "
                f"{_fmt(r.summary.get('water_level_m'), '.3f')} m, {hid}, {r.item.out_dir}"
            )
    for r in res.failed:
        print(f"  FAILED  {r.item.label}: {r.error}")
    return 1 if res.failed else 0


# ---------------------------------------------------------------------------------------------


def register(sub: argparse._SubParsersAction) -> None:
    """Add `site`, `history`, `report` and `batch` to the fieldtool command line."""
    _register_site(sub)
    _register_history(sub)
    _register_report(sub)
    _register_batch(sub)


def _register_site(sub: argparse._SubParsersAction) -> None:
    """`fieldtool site create | list | show | new-measurement`."""
    p = sub.add_parser("site", help="sites: the fixed inputs of a station (create, list, show, new-measurement)")
    ss = p.add_subparsers(dest="site_command", metavar="SITE_COMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    q = ss.add_parser("create", help="make a site from a project (cross-section, GCPs, lens, ROI, parameters)")
    q.add_argument("name", help="site name (letters, digits, '.', '_', '-')")
    q.add_argument(
        "--from",
        dest="from_project",
        required=True,
        metavar="PROJECT",
        help="project file (or a run's result.json) whose fixed inputs the site keeps",
    )
    q.add_argument("--description", help="free text (where, who, datum)")
    q.add_argument("--force", action="store_true", help="replace an existing site of that name")
    _add_sites(q)
    q.set_defaults(func=cmd_site_create)

    q = ss.add_parser("list", help="list the sites")
    _add_sites(q)
    q.set_defaults(func=cmd_site_list)

    q = ss.add_parser("show", help="show what a site holds")
    q.add_argument("name")
    q.add_argument("--toml", action="store_true", help="print site.toml as it is")
    _add_sites(q)
    q.set_defaults(func=cmd_site_show)

    q = ss.add_parser("new-measurement", help="a new visit: a project from the site, a video and a water level")
    q.add_argument("name", help="site name")
    q.add_argument("--video", required=True, help="the new video")
    q.add_argument("--level", type=float, help="water level (m, datum of the site's cross-section)")
    q.add_argument("--level-uncertainty", type=float, help="how sure the level is (m)")
    q.add_argument("--out", help="folder for the new project (default ./SITE_VIDEONAME)")
    q.add_argument("--force", action="store_true", help="overwrite a project.toml already in --out")
    q.add_argument("--run", action="store_true", help="also run it, record it in the history and write report.html")
    _add_sites(q)
    _add_db(q)
    q.set_defaults(func=cmd_site_new_measurement)


def _register_history(sub: argparse._SubParsersAction) -> None:
    """`fieldtool history list | show | export | add | reference | delete | stats | rating`."""
    p = sub.add_parser("history", help="measurement history: list, show, export, add, reference, stats, rating")
    hs = p.add_subparsers(dest="history_command", metavar="HISTORY_COMMAND")
    _add_db(p)
    p.set_defaults(func=cmd_history_list, site=None, since=None, until=None, limit=50)

    q = hs.add_parser("list", help="list measurements, newest first")
    _add_filters(q)
    q.add_argument("--limit", type=int, default=None, help="at most this many rows")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_list)

    q = hs.add_parser("show", help="one measurement in full")
    q.add_argument("id", type=int)
    q.add_argument("--parameters", action="store_true", help="also print the parameters (JSON)")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_show)

    q = hs.add_parser("export", help="write measurements (and their references) as CSV")
    q.add_argument("file", help="CSV file to write, or - for standard output")
    _add_filters(q)
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_export)

    q = hs.add_parser("add", help="record a run made with `fieldtool run` (its output folder)")
    q.add_argument("result_dir", help="output folder holding result.json")
    q.add_argument("--site", help="site name to record it under")
    q.add_argument("--project", help="the project file it was run from (default: the folder above the results)")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_add)

    q = hs.add_parser("reference", help="attach a reference discharge (current meter, ADCP, gauge) to a measurement")
    q.add_argument("id", type=int, help="measurement id (see `fieldtool history list`)")
    q.add_argument("discharge", type=float, help="reference discharge (m3/s)")
    q.add_argument("--method", required=True, choices=["current_meter", "adcp", "gauge", "other"])
    q.add_argument("--uncertainty", type=float, help="its uncertainty (m3/s)")
    q.add_argument("--note", help="free text")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_reference)

    q = hs.add_parser("delete", help="delete a measurement (and its references) from the history")
    q.add_argument("id", type=int)
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_delete)

    q = hs.add_parser("stations", help="per fixed-camera station: clips done, pending and failed")
    q.add_argument("--site", help="only this site")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_stations)

    q = hs.add_parser("stats", help="per site: error of LSPIV against the reference discharges")
    q.add_argument("--site", help="only this site")
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_stats)

    q = hs.add_parser("rating", help="stage-discharge curve Q = a (h - h0)^b of a site, with a plot")
    q.add_argument("site")
    q.add_argument("--out", help="plot file (.png, .pdf or .svg; default ./rating_SITE.png)")
    q.add_argument("--h0", type=float, help="level of zero flow (m) when known; default: fitted below the lowest level")
    q.add_argument(
        "--fit-to",
        choices=["measured", "reference"],
        default="measured",
        help="fit the LSPIV discharges (default) or the reference discharges",
    )
    _add_db(q, under_history=True)
    q.set_defaults(func=cmd_history_rating)


def _register_report(sub: argparse._SubParsersAction) -> None:
    """`fieldtool report`."""
    p = sub.add_parser("report", help="self-contained HTML report (and PDF) of a measurement")
    p.add_argument("result_dir", nargs="?", help="a run's output folder (holds result.json)")
    p.add_argument("--id", type=int, help="or: a measurement id from the history")
    p.add_argument("--out", help="HTML file (default report.html in the output folder)")
    p.add_argument("--pdf", action="store_true", help="also write a PDF beside the HTML")
    _add_db(p)
    p.set_defaults(func=cmd_report)


def _register_batch(sub: argparse._SubParsersAction) -> None:
    """`fieldtool batch`."""
    p = sub.add_parser("batch", help="run many measurements on all local cores or a Dask cluster")
    p.add_argument("projects", nargs="*", help="project files to run")
    p.add_argument("--list", help="text file with one project file per line")
    p.add_argument("--site", help="site: with --videos, the site to measure; else the site to record the runs under")
    p.add_argument("--videos", help="folder of videos of --site, one measurement each")
    p.add_argument("--levels", help="with --videos: CSV with columns video,water_level_m")
    p.add_argument("--level", type=float, help="with --videos: one water level (m) for every video")
    p.add_argument("--level-uncertainty", type=float, help="with --videos: level uncertainty (m)")
    p.add_argument("--out", help="output root (default: --videos FOLDER/fieldtool_out; projects: out/ beside each)")
    p.add_argument("--workers", type=int, help="local processes (default: all cores)")
    p.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT; workers must see the same paths")
    p.add_argument("--skip-existing", action="store_true", help="skip items whose inputs are already in the history")
    p.add_argument("--report", action="store_true", help="also write report.html into each output folder")
    p.add_argument("--no-history", action="store_true", help="do not record the runs")
    _add_sites(p)
    _add_db(p)
    p.set_defaults(func=cmd_batch)
