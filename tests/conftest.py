"""Shared fixtures: a short synthetic scene rendered once per session.

tests/ mirrors the package (tests/run/ for fieldtool/run/, ...), plus tests/accuracy/ (whole synthetic scenes
with known truth) and tests/docs/. Some test modules import helpers from others (``test_tui_snapshots``'s
``make_project``, ``test_viewer_server``'s ``_tiny_project``): every test folder is put on the path here, so
they do so by module name whatever folder they sit in, as they did when tests/ was flat.
"""

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
SHARED_DATA = HERE.parent / ".." / "shared" / "data"
#: tests that wait on wall-clock time (a browser's page, a server's answer, a process killed at a moment, two
#: editors interleaving): ``make test`` runs them alone after the rest, which runs on every core (pytest-xdist),
#: so that no other test's load stretches their waits. Files relative to tests/.
SERIAL = (
    "tui/test_tui_app.py",
    "tui/test_two_editors.py",
    "viewer/test_viewer_hardening.py",
    "viewer/test_viewer_security.py",
    "viewer/test_viewer_server.py",
    "viewer/test_rerun_log.py",
    "run/test_outputs_safety.py",
    "run/test_overlay.py",
    "records/test_station.py",
)

for _folder in sorted(HERE.iterdir()):
    if _folder.is_dir() and not _folder.name.startswith(("_", ".")) and str(_folder) not in sys.path:
        sys.path.append(str(_folder))


def pytest_collection_modifyitems(config, items):
    """Mark the :data:`SERIAL` tests (and every browser test) ``serial``."""
    for item in items:
        rel = item.path.resolve().relative_to(HERE).as_posix()
        if item.get_closest_marker("browser") or rel in SERIAL:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="session")
def short_scene(tmp_path_factory):
    """A 1.2 s oblique scene (project.toml, video, cross-section, truth) rendered once."""
    from fieldtool.synthetic import presets, render_scene

    out = tmp_path_factory.mktemp("short_scene")
    truth = render_scene(presets.get("oblique", duration_s=1.2), out)
    return truth


@pytest.fixture(scope="session")
def rendered(tmp_path_factory):
    """``rendered(name, **overrides)``: the preset's scene (its truth), rendered once per session for each
    (name, overrides). Shared: a test runs it into a folder of its own and never writes into the scene's."""
    from fieldtool.synthetic import presets, render_scene

    cache = {}

    def get(name, **overrides):
        key = (name, tuple(sorted(overrides.items())))
        if key not in cache:
            cache[key] = render_scene(presets.get(name, **overrides), tmp_path_factory.mktemp(f"rendered_{name}"))
        return cache[key]

    return get


@pytest.fixture
def scene(short_scene, tmp_path):
    """A copy of the short scene's files in this test's own folder (its outputs and edits stay there)."""
    import shutil

    src = short_scene.project_path.parent
    for f in src.iterdir():
        if f.is_file():
            shutil.copy(f, tmp_path / f.name)
    return tmp_path
