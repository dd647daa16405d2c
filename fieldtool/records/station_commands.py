"""`fieldtool station SITE --incoming DIR` (watch and measure), `fieldtool station status SITE --incoming DIR`
(done, pending, failed) and `fieldtool station retry SITE --incoming DIR [--clip NAME]` (failed clips again).
See :mod:`fieldtool.records.station`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.records.commands import _add_db, _add_sites
from fieldtool.records.history import History, resolve_db_path
from fieldtool.records.sites import load_site, sites_dir

ACTIONS = ("status", "retry")


def _incoming(args) -> Path:
    p = Path(args.incoming).expanduser()
    if not p.is_dir():
        raise InputFileError(f"--incoming {p}: not a folder; give the folder the camera writes its clips into")
    return p.resolve()


def _print(line: str) -> None:
    print(line, flush=True)


def _station():
    """records.station, lazy: it imports the whole run (numpy, OpenCV, SciPy), which building the command line's
    parser (every command's options, `fieldtool run` included) must not wait for."""
    from fieldtool.records import station

    return station


def cmd_station(args) -> int:
    st = _station()
    words = list(args.words)
    action = words.pop(0) if len(words) == 2 and words[0] in ACTIONS else "watch"
    if len(words) != 1:
        raise ParameterError(
            "give: fieldtool station SITE --incoming DIR (or station status|retry SITE --incoming DIR)"
        )
    root = sites_dir(args.sites)
    site = load_site(words[0], root)
    incoming = _incoming(args)
    db = resolve_db_path(args.db)
    if action == "status":
        return _status(site.name, incoming, db)
    with History(db) as hist:
        if action == "retry":
            n = st.retry_failed(hist, site.name, incoming, args.clip)
            print(
                f"{n} failed clip(s) put back to pending; a running station measures them within "
                f"{st.StationConfig().poll_s:g} s, else the next `fieldtool station {site.name}` does"
            )
            return 0
        cfg = st.station_config(
            site,
            level_order=args.level_order,
            level_file=args.level_file,
            gauge_m=args.gauge,
            level_uncertainty_m=args.level_uncertainty,
            stable_s=args.stable_s,
            poll_s=args.poll_s,
        )
        station = st.Station(
            site,
            root,
            incoming,
            hist,
            cfg,
            out_root=Path(args.out) if args.out else None,
            dask=args.dask,
            rerun=args.rerun,
            log=_print,
        )
        st.install_signal_handlers(station)
        return station.run(max_idle_s=args.exit_when_idle)


def _status(site: str, incoming: Path, db: Path) -> int:
    st = _station()
    if not db.exists():
        print(f"no history yet ({db}): nothing measured", file=sys.stderr)
        rows = st.StationStatus(
            [], [], [], [str(p) for p in st.clip_files(incoming)], st.StationLock(incoming).held_by_other()
        )
    else:
        with History(db, create=False) as hist:
            rows = st.status(hist, site, incoming)
    print(f"station {site} on {incoming}: " + (f"running (process {rows.held_by})" if rows.held_by else "not running"))
    print(f"done     {len(rows.done)}")
    for r in rows.done:
        print(f"  {Path(r.path).name:<32} measurement {r.measurement_id}  level from {r.level_source}  {r.updated_at}")
    print(f"pending  {len(rows.pending) + len(rows.running)}")
    for r in rows.running:
        print(f"  {Path(r.path).name:<32} " + ("in flight" if rows.held_by else "left in flight by a stopped station"))
    for p in rows.pending:
        print(f"  {Path(p).name}")
    print(
        f"failed   {len(rows.failed)}"
        + (f"  (retry: fieldtool station retry {site} --incoming {incoming})" if rows.failed else "")
    )
    for r in rows.failed:
        print(f"  {Path(r.path).name:<32} {r.reason}")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "station",
        help="fixed camera: measure every new clip of a folder with a site (status, retry)",
        description="fieldtool station SITE --incoming DIR: watch DIR and measure each complete clip "
        "with the site's fixed geometry. fieldtool station status SITE --incoming DIR: "
        "done, pending and failed clips. fieldtool station retry SITE --incoming DIR: "
        "failed clips again.",
    )
    p.add_argument("words", nargs="+", metavar="[status|retry] SITE", help="the site (after status or retry)")
    p.add_argument("--incoming", required=True, help="folder the camera writes its clips into")
    p.add_argument("--out", help="results, time series and rating plots (default INCOMING/fieldtool_station)")
    p.add_argument(
        "--level-order",
        help="level sources to try, in order: waterline,file,gauge (default: the "
        "site's [station] level_sources, else that order)",
    )
    p.add_argument("--level-file", help="CSV of time,level (ISO 8601 UTC or Unix seconds, m)")
    p.add_argument("--gauge", type=float, help="a gauge reading (m, datum of the site's cross-section)")
    p.add_argument("--level-uncertainty", type=float, help="how sure the file or gauge level is (m)")
    p.add_argument(
        "--stable-s",
        type=float,
        help="a clip is complete when unchanged this long (s, default 5), or at once with a CLIP.done marker",
    )
    p.add_argument("--poll-s", type=float, help="how often the folder is looked at (s, default 1)")
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="run the clips on this Dask scheduler (tcp://HOST:PORT), as `batch --scheduler`",
    )
    p.add_argument(
        "--rerun",
        metavar="FILE_OR_URL",
        help="stream the series: a .rrd file or a viewer address rerun+http://HOST:9876/proxy",
    )
    p.add_argument("--exit-when-idle", type=float, metavar="S", help=argparse.SUPPRESS)  # tests, cron: stop when idle
    p.add_argument("--clip", help="with retry: only this clip (file name)")
    _add_sites(p)
    _add_db(p)
    p.set_defaults(func=cmd_station)
