"""Project file: round trip, atomic save, clear errors for unknown keys and wrong types."""

import os
from pathlib import Path

import pytest

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.project.model import Project, load_project, project_from_dict, project_to_dict, save_project
from fieldtool.project.template import (
    KEYS_BEGIN,
    KEYS_END,
    KEYS_PAGE,
    key_table_markdown,
    template_text,
    update_keys_page,
)


def test_round_trip(tmp_path):
    p = Project(name="site A")
    p.ortho.gcp_px = [[1.5, 2.0], [3, 4], [5, 6], [7, 8]]
    p.ortho.distances_m = [1, 2, 3, 4, 5, 6]
    p.video.end_s = 4.5
    p.filters = [{"name": "clahe", "clip_limit": 2.0}]
    path = tmp_path / "project.toml"
    save_project(p, path)
    q = load_project(path)
    assert project_to_dict(q) == project_to_dict(p)
    assert q.root == tmp_path.resolve()
    assert q.video.end_s == 4.5 and q.piv.search_px is None


def test_unknown_key_names_the_key():
    with pytest.raises(ParameterError, match=r"unknown key piv\.windw_px"):
        project_from_dict({"piv": {"windw_px": 32}})


def test_wrong_type_names_the_key():
    with pytest.raises(ParameterError, match=r"piv\.window_px: expected a whole number"):
        project_from_dict({"piv": {"window_px": "32"}})
    with pytest.raises(ParameterError, match=r"ortho\.gcp_px\[1\]\[0\]: expected a number"):
        project_from_dict({"ortho": {"gcp_px": [[1, 2], ["a", 3]]}})


def test_bad_toml_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[piv\nwindow_px = 3")
    with pytest.raises(InputFileError, match="bad.toml: not valid TOML"):
        load_project(path)


def test_atomic_save_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "project.toml"
    save_project(Project(name="first"), path)
    before = path.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        save_project(Project(name="second"), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["project.toml"]  # no temp file left


def test_template_loads_and_documents_every_key(tmp_path):
    path = tmp_path / "project.toml"
    path.write_text(template_text())
    assert project_to_dict(load_project(path)) == project_to_dict(Project())
    table = key_table_markdown()
    for section, keys in project_to_dict(Project()).items():
        if isinstance(keys, dict):
            for k in keys:
                assert f"`{section}.{k}`" in table


def test_keys_page_documents_every_key():
    """docs/keys.md holds the table the key declarations give today (regenerate it with --docs)."""
    text = KEYS_PAGE.read_text(encoding="utf-8")
    assert KEYS_PAGE == Path(__file__).resolve().parents[2] / "docs" / "keys.md"
    table = text.split(KEYS_BEGIN, 1)[1].split(KEYS_END, 1)[0].strip()
    assert table == key_table_markdown(), "run `python -m fieldtool.project.template --docs`"


def test_keys_page_update_rewrites_only_the_table(tmp_path):
    """The generator replaces a stale table between the markers and keeps the page's own text."""
    page = tmp_path / "keys.md"
    page.write_text(f"# Keys\n\nintro\n\n{KEYS_BEGIN}\n| stale |\n{KEYS_END}\n\nafter\n", encoding="utf-8")
    assert update_keys_page(page) is True
    text = page.read_text(encoding="utf-8")
    assert text.startswith("# Keys\n\nintro\n\n") and text.endswith("\n\nafter\n")
    assert "| stale |" not in text and key_table_markdown() in text
    assert update_keys_page(page) is False
