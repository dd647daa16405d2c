"""Sites: what does not change between visits to a station.

A site is a folder ``<sites folder>/<name>/`` holding ``site.toml`` and copies of the files it needs
(cross-section, lens calibration, bank DEM). ``site.toml`` has a ``[site]`` table (name, description,
times, where it came from) and a ``[project]`` table: a project file without the per-visit inputs
(video, typed water level, water-edge picks), whose relative paths are relative to the site folder.
The cross-section, GCPs (pixels and distances or world coordinates), calibration, ROI and masks,
stable regions, filters and PIV/section parameters all stay.

Sites are plain files rather than rows in the history database: they are read and edited like
project files, copied between field laptops and shared with cluster workers as a folder, and a
damaged history cannot take the site definitions with it.

The sites folder is ``--sites DIR``, else ``FIELDTOOL_SITES``, else ``<user data folder>/sites``.
"""

from __future__ import annotations

import copy
import json
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing.cross_section import load_cross_section
from fieldtool.processing.paths import is_pattern
from fieldtool.project.model import (
    Project,
    atomic_write_bytes,
    load_project,
    project_from_dict,
    project_to_dict,
)
from fieldtool.project.sync import ProjectSync
from fieldtool.project.validation import check
from fieldtool.records import user_data_dir
from fieldtool.records.history import utc_now

SITE_FILE = "site.toml"
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")  # used with fullmatch: "$" lets a final newline in

# (table, key, stored file stem): input files that belong to the site and are copied with it
SITE_FILES = (
    ("cross_section", "path", "cross_section"),
    ("calibration", "path", "calibration"),
    ("water_level", "dem_path", "dem"),
)

# per-visit inputs, removed from the site's project
_PER_VISIT = {
    "video": ("path",),
    "water_level": (
        "value_m",
        "width_m",
        "edges_px",
        "edges1_px",
        "edges2_px",
        "image1",
        "image2",
        "height_m",
        "dh_m",
        "divergence_station_m",
    ),
    "calibration": ("checkerboard_video",),  # the lens model (calibration.path) is what is kept
}


@dataclass
class Site:
    """A station's fixed inputs.

    Attributes
    ----------
    name : short name, also the folder name (letters, digits, '.', '_', '-').
    folder : the site's folder.
    project : project dict without per-visit inputs; relative paths relative to ``folder``.
    description, created_at, updated_at, source : free text, ISO 8601 UTC times, the project
        file the site was made from.
    """

    name: str
    folder: Path
    project: dict = field(default_factory=dict)
    description: str = ""
    created_at: str = ""
    updated_at: str = ""
    source: str = ""

    def template(self) -> Project:
        """The site's project (no video, no level), relative paths resolved from the site folder."""
        try:
            return project_from_dict(copy.deepcopy(self.project), self.folder)
        except ParameterError as e:
            raise ParameterError(f"{self.folder / SITE_FILE}: [project] {e}") from e


def sites_dir(arg: str | Path | None = None) -> Path:
    """The sites folder: ``arg``, else ``FIELDTOOL_SITES``, else ``<user data folder>/sites``."""
    if arg:
        return Path(arg).expanduser()
    env = os.environ.get("FIELDTOOL_SITES", "").strip()
    return Path(env).expanduser() if env else user_data_dir() / "sites"


def check_name(name: str) -> str:
    """The name when it can be a site (and folder) name; else ParameterError naming the fault."""
    bad = [c for c in (name or "") if ord(c) < 32 or ord(c) == 127]
    if bad:
        raise ParameterError(
            f"site name {name!r}: contains a control character ({bad[0]!r}); use 1-64 letters, digits, '.', '_' or '-'"
        )
    if not _NAME_RE.fullmatch(name or ""):
        raise ParameterError(
            f"site name {name!r}: use 1-64 letters, digits, '.', '_' or '-', starting with a letter "
            "or digit (it becomes a folder name)"
        )
    return name


@dataclass
class BrokenSite:
    """A site folder whose ``site.toml`` cannot be used, and why."""

    name: str
    folder: Path
    reason: str


def list_sites(root: Path | str, broken: list[BrokenSite] | None = None) -> list[Site]:
    """Every readable site in the sites folder, by name. A site whose ``site.toml`` is damaged
    (or whose folder name cannot be a site name) is left out of the list and, when ``broken`` is
    given, appended to it with the reason; it never hides the other sites."""
    root = Path(root)
    if not root.is_dir():
        return []
    out = []
    for p in sorted(root.iterdir()):
        if not (p / SITE_FILE).is_file():
            continue
        try:
            out.append(load_site(p.name, root))
        except (ParameterError, InputFileError) as e:
            if broken is not None:
                broken.append(BrokenSite(p.name, p, str(e)))
    return out


def load_site(name: str, root: Path | str) -> Site:
    """Read one site. An unknown name raises ParameterError listing the known ones."""
    root = Path(root)
    path = root / name / SITE_FILE
    if not _NAME_RE.fullmatch(name or "") or not path.is_file():
        known = sorted(p.name for p in root.iterdir() if (p / SITE_FILE).is_file()) if root.is_dir() else []
        hint = f"known sites: {', '.join(known)}" if known else f"no sites in {root} yet"
        raise ParameterError(
            f"site {name!r} not found ({hint}); create it with "
            "`fieldtool site create NAME --from PROJECT.toml` or give the folder with --sites"
        )
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputFileError(f"{path}: not valid TOML ({e}); fix it or re-create the site with --force") from e
    except OSError as e:
        raise InputFileError(f"{path}: cannot be read ({e.strerror})") from e
    meta = data.get("site", {})
    proj = data.get("project")
    if not isinstance(meta, dict) or not isinstance(proj, dict):
        raise InputFileError(f"{path}: needs a [site] and a [project] table; re-create the site with --force")
    site = Site(
        name=name,
        folder=path.parent,
        project=proj,
        description=str(meta.get("description", "")),
        created_at=str(meta.get("created_at", "")),
        updated_at=str(meta.get("updated_at", "")),
        source=str(meta.get("source", "")),
    )
    site.template()  # validates the [project] table, naming a bad key
    return site


def create_site(
    name: str, project: Project, root: Path | str, *, description: str = "", force: bool = False, source: str = ""
) -> Site:
    """Make (or with ``force`` replace) a site from a project: copies its cross-section,
    calibration and DEM files into the site folder and keeps everything but the per-visit inputs.

    Raises
    ------
    ParameterError : bad name, the site exists and ``force`` is False, or the project has no cross-section.
    InputFileError : a file the project names is missing.
    """
    check_name(name)
    folder = Path(root) / name
    old = None
    if (folder / SITE_FILE).exists():
        if not force:
            raise ParameterError(f"site {name!r} already exists in {folder}; use --force to replace it")
        old = load_site(name, root)
    d = strip_per_visit(project_to_dict(project))
    cs = d.get("cross_section", {})
    if not cs.get("shape") and not cs.get("path"):
        raise ParameterError("cross_section: the project has no cross-section (path or shape); a site needs one")
    blobs: dict[str, bytes] = {}
    for table, key, stem in SITE_FILES:
        rel = d.get(table, {}).get(key)
        if not rel:
            continue
        src = project.resolve(rel)
        if not src.is_file():
            raise InputFileError(f"{src}: {table}.{key} names this file but it is not there; fix the project first")
        fname = stem + src.suffix.lower()
        blobs[fname] = src.read_bytes()
        d[table][key] = fname
    folder.mkdir(parents=True, exist_ok=True)
    for fname, blob in blobs.items():
        atomic_write_bytes(folder / fname, blob)
    now = utc_now()
    site = Site(
        name=name,
        folder=folder,
        project=d,
        description=description,
        created_at=old.created_at if old else now,
        updated_at=now,
        source=source,
    )
    site.template()
    save_site(site)
    return site


def save_site(site: Site) -> None:
    meta = {
        "name": site.name,
        "description": site.description,
        "created_at": site.created_at,
        "updated_at": site.updated_at,
        "source": site.source,
    }
    blob = tomli_w.dumps({"site": meta, "project": site.project}).encode("utf-8")
    atomic_write_bytes(site.folder / SITE_FILE, blob)


def strip_per_visit(d: dict) -> dict:
    """A copy of a project dict without the per-visit inputs (video, typed level, edge picks)."""
    d = copy.deepcopy(d)
    for table, keys in _PER_VISIT.items():
        for k in keys:
            d.get(table, {}).pop(k, None)
    d.pop("step", None)
    d.pop("site", None)  # the site is the folder it is stored in
    return d


def measurement_dict(
    site: Site,
    video: Path | str,
    level_m: float | None,
    out_dir: Path | str,
    *,
    level_uncertainty_m: float | None = None,
    name: str | None = None,
) -> dict:
    """The project dict of a new visit, for a project file written in ``out_dir``.

    The site's files are referred to where the visit's folder will hold copies (same names);
    the video by a path relative to ``out_dir`` when it lies below it, else absolute."""
    if level_m is None and site.project.get("water_level", {}).get("method", "value") == "value":
        raise ParameterError(
            f"site {site.name!r} takes a typed water level: give it with --level (m, in the "
            "datum of the site's cross-section)"
        )
    d = copy.deepcopy(site.project)
    video = Path(video).expanduser().absolute()
    out_dir = Path(out_dir).absolute()
    try:
        vpath = str(video.relative_to(out_dir))
    except ValueError:
        vpath = str(video)
    d.setdefault("video", {})["path"] = vpath
    if level_m is not None:
        wl = d.setdefault("water_level", {})
        wl["method"] = "value"
        wl["value_m"] = float(level_m)
        if level_uncertainty_m is not None:
            wl["uncertainty_m"] = float(level_uncertainty_m)
    d["name"] = name or f"{site.name} {video.stem}"
    d["step"] = "discharge"
    return d


def new_measurement(
    site: Site,
    video: Path | str,
    level_m: float | None,
    out_dir: Path | str,
    *,
    level_uncertainty_m: float | None = None,
    name: str | None = None,
    force: bool = False,
) -> Path:
    """Write ``out_dir/project.toml`` for a new visit of ``site`` with copies of the site's files.

    Only the video and the water level (m) are new; everything else comes from the site.
    Returns the project file's path; run it with ``fieldtool run`` or :func:`fieldtool.run.pipeline.run_project`.

    Raises
    ------
    InputFileError : the video is missing, or out_dir already has a project.toml (without ``force``).
    ParameterError : no level given for a site that takes a typed level.
    """
    video = Path(video).expanduser()
    if not video.exists() and not is_pattern(video):
        raise InputFileError(f"{video}: video not found")
    out_dir = Path(out_dir)
    proj_path = out_dir / "project.toml"
    if proj_path.exists() and not force:
        raise InputFileError(f"{proj_path}: already exists; choose another folder or use --force")
    d = measurement_dict(site, video, level_m, out_dir, level_uncertainty_m=level_uncertainty_m, name=name)
    project = project_from_dict(d, out_dir.absolute())
    project.site = site.name
    check(project, files=False, prefix="water_level.")  # --level nan/inf, a negative uncertainty: the one layer's word
    for table, key, _stem in SITE_FILES:
        rel = d.get(table, {}).get(key)
        if rel:
            atomic_write_bytes(out_dir / rel, (site.folder / rel).read_bytes())
    ProjectSync(proj_path).save(project)  # an existing (--force) read-only or invalid file is refused
    return proj_path


def load_site_project(path: Path | str) -> Project:
    """The project a site is created from (a project.toml or a run's result.json ``inputs``)."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        try:
            inputs = json.loads(path.read_text(encoding="utf-8"))["inputs"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputFileError(f"{path}: not a result.json with an 'inputs' table ({e})") from e
        return project_from_dict(inputs, path.resolve().parent.parent)
    return load_project(path)


def describe(site: Site) -> list[str]:
    """Human-readable lines about a site (for `fieldtool site show`)."""
    p = site.template()
    lines = [f"site          {site.name}", f"folder        {site.folder}"]
    if site.description:
        lines.append(f"description   {site.description}")
    lines.append(f"created       {site.created_at}   updated {site.updated_at}")
    if site.source:
        lines.append(f"made from     {site.source}")
    cs = p.cross_section
    if cs.shape:
        lines.append(f"cross-section {cs.shape}, top width {cs.top_width_m} m, depth {cs.depth_m} m")
    else:
        try:
            x = load_cross_section(p.resolve(cs.path))
            lines.append(
                f"cross-section {cs.path}: {len(x.station)} points, stations {x.station.min():.2f}-"
                f"{x.station.max():.2f} m, lowest bed {x.bed_min:.3f} m"
            )
        except (InputFileError, ParameterError) as e:
            lines.append(f"cross-section {cs.path}: cannot be read ({e})")
    o = p.ortho
    gcp = f"{len(o.gcp_px)} GCPs" + (
        f", distances {', '.join(f'{v:.3f}' for v in o.distances_m)} m" if o.distances_m else ""
    )
    lines.append(f"ortho         {o.method}: {gcp}")
    lines.append(f"calibration   {p.calibration.path or '(none: no lens correction)'}")
    lines.append(
        f"water level   method {p.water_level.method}"
        + (f", uncertainty {p.water_level.uncertainty_m} m" if p.water_level.uncertainty_m is not None else "")
    )
    lines.append(f"ROI           {p.roi.rect_px or 'whole frame'}; {len(p.roi.masks_px)} mask(s)")
    st = p.stabilize
    lines.append(f"stabilise     {'on' if st.enabled else 'off'}; {len(st.regions_px)} stable region(s)")
    lines.append(f"filters       {', '.join(f.get('name', '?') for f in p.filters) or 'none'}")
    pv = p.piv
    lines.append(
        f"PIV           window {pv.window_px} px, overlap {pv.overlap_px} px, {pv.passes} pass(es), engine {pv.engine}"
    )
    se = p.section
    lines.append(
        f"section       {len(se.points_px)} points, {se.n_sub} subsections, alpha "
        f"{se.alpha if se.alpha is not None else 'automatic'}"
    )
    v = p.video
    lines.append(f"clip          from {v.start_s} s to {v.end_s if v.end_s is not None else 'end'}, step {v.step}")
    return lines
