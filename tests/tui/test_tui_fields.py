"""TUI parameters: every field maps to a real project key, parses what a person types, and
rejects bad entries with a message naming the key."""

import dataclasses

import pytest

from fieldtool.project.model import Project, project_from_dict, project_to_dict
from fieldtool.tui.fields import Field, fmt_num
from fieldtool.tui.session import Session
from fieldtool.tui.steps import STEPS, fields_for


def all_fields():
    seen = []
    for mode in ("skip", "load", "run"):
        for s in STEPS:
            for f in fields_for(s.id, {"calibration_mode": mode}):
                if f not in seen:
                    seen.append(f)
    return seen


@pytest.mark.parametrize("field", all_fields(), ids=lambda f: f.key)
def test_every_field_is_a_project_key_with_unit_help_and_round_trip(field: Field):
    p = Project()
    field.get(p)  # the key exists in the project model
    assert field.help and field.label
    if field.kind == "choice":
        assert field.choices and field.get(p) in [v for _, v in field.choices]
    # what the TUI shows for the default reads back to the same value
    d = field.get(p)
    if field.kind != "choice" and d is not None:
        assert field.parse(field.format(d)) == d
    if d is None and not field.nullable():  # an item of a list: empty is refused, not stored
        with pytest.raises(ValueError, match="a value is needed"):
            field.parse("")


def test_numbers_round_trip_exactly():
    for v in (0.1, 1e-7, 123456.789, 10.0, -2.5, 1 / 3):
        assert float(fmt_num(v)) == v


def find(key, mode="skip"):
    for s in STEPS:
        for f in fields_for(s.id, {"calibration_mode": mode}):
            if f.key == key:
                return f
    raise KeyError(key)


@pytest.mark.parametrize(
    "key,text,expect",
    [
        ("video.start_s", "abc", "video.start_s: 'abc' is not a number"),
        ("video.start_s", "-1", "must be 0 or more"),
        ("video.end_s", "0", "must be after the start"),
        ("video.step", "1.5", "not a whole number"),
        ("video.step", "0", "too small"),
        ("ortho.gcp_px[0]", "12", "give 2 numbers: x, y"),
        ("ortho.distances_m[0]", "-3", "must be greater than 0"),
        ("piv.overlap_px", "32", "less than the window (32 px)"),
        ("piv.window_px", "4", "too small"),
        ("piv.min_valid_fraction", "1.5", "out of range"),
        ("roi.rect_px", "10, 10, 5, 50", "x1 > x0"),
        ("roi.masks_px", "1, 2; 3, 4", "at least 3 points"),
        ("section.alpha", "2", "out of range"),
        ("cross_section.top_width_m", "0", "greater than 0"),
        ("water_level.dem_x_m", "5, 1", "must exceed the first"),
    ],
)
def test_invalid_entries_have_messages_naming_the_key(key, text, expect):
    f = find(key)
    p = Project()
    p.cross_section.shape = "trapezoidal"
    p.water_level.method = "dem"
    _, msg = f.text_error(text, p)
    assert msg is not None and msg.startswith(key) and expect in msg


def test_empty_unsets_only_optional_keys():
    assert find("video.end_s").parse("") is None
    with pytest.raises(ValueError, match="a value is needed .default 0."):
        find("video.start_s").parse("")


def test_required_depends_on_the_choice():
    p = Project()
    p.water_level.method = "value"
    f = find("water_level.value_m")
    assert "required" in f.validate(None, p)
    p.water_level.method = "width"
    assert not f.visible(p)
    assert find("water_level.width_m").validate(None, p) is not None


def test_indexed_items_are_kept_in_order():
    p = Project()
    f0, f2 = find("ortho.gcp_px[0]"), find("ortho.gcp_px[2]")
    assert "enter item 1 first" in f2.validate([1.0, 2.0], p)
    f0.set(p, [1.0, 2.0])
    assert p.ortho.gcp_px == [[1.0, 2.0]]
    f0.set(p, [3.0, 4.0])
    assert p.ortho.gcp_px == [[3.0, 4.0]]


def test_new_project_is_created_and_saved(tmp_path):
    s = Session(tmp_path / "m" / "project.toml")
    assert s.path.is_file()
    assert s.project.step == "cross_section"
    # every table of a fresh project survives the file
    assert project_to_dict(project_from_dict(project_to_dict(s.project))) == project_to_dict(s.project)
    assert dataclasses.is_dataclass(s.project)
