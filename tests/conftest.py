"""Shared fixtures: a short synthetic scene rendered once per session."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


@pytest.fixture(scope="session")
def short_scene(tmp_path_factory):
    """A 1.2 s oblique scene (project.toml, video, cross-section, truth) rendered once."""
    from fieldtool.synthetic import presets, render_scene

    out = tmp_path_factory.mktemp("short_scene")
    truth = render_scene(presets.get("oblique", duration_s=1.2), out)
    return truth


@pytest.fixture
def scene(short_scene, tmp_path):
    """A copy of the short scene's files in this test's own folder (its outputs and edits stay there)."""
    import shutil

    src = short_scene.project_path.parent
    for f in src.iterdir():
        if f.is_file():
            shutil.copy(f, tmp_path / f.name)
    return tmp_path
