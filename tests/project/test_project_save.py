"""Round-trip saving (comments kept) and concurrent writers (ProjectSync.set_keys never loses a key)."""

import multiprocessing as mp
from pathlib import Path

from fieldtool.project.model import load_project, save_project
from fieldtool.project.sync import ProjectSync
from fieldtool.project.template import write_template


def test_template_comments_survive_edits(tmp_path):
    path = write_template(tmp_path)
    before = [ln for ln in path.read_text().splitlines() if ln.lstrip().startswith("#") or "  # " in ln]
    p = load_project(path)
    p.video.path = "clip.mp4"
    p.video.end_s = 4.0
    p.filters = [{"name": "clahe"}]
    save_project(p, path)
    ProjectSync(path).set_keys({"section.n_sub": 20, "name": "Mesure à l'écluse"})
    text = path.read_text(encoding="utf-8")
    # every comment line of the template is still there, and the edited keys kept their comments
    assert all(ln in text for ln in before if ln.lstrip().startswith("#") and "end_s" not in ln)
    assert 'path = "clip.mp4"  # video file' in text
    assert 'filters = [{name = "clahe"}]  # ordered stack' in text
    q = load_project(path)
    assert (q.video.end_s, q.section.n_sub, q.name, q.filters) == (4.0, 20, "Mesure à l'écluse", [{"name": "clahe"}])


def _writer(path, key, n):
    for i in range(n):
        ProjectSync(path).set_keys({key: float(i + 1)})


def test_two_writers_keep_each_others_keys(tmp_path):
    path = write_template(tmp_path)
    ctx = mp.get_context("fork")
    a = ctx.Process(target=_writer, args=(str(path), "video.start_s", 30))
    b = ctx.Process(target=_writer, args=(str(path), "water_level.value_m", 30))
    a.start(), b.start()
    a.join(60), b.join(60)
    assert a.exitcode == 0 and b.exitcode == 0
    p = load_project(path)
    assert p.video.start_s == 30.0 and p.water_level.value_m == 30.0


def test_tui_session_keeps_a_key_another_process_set(tmp_path):
    from fieldtool.tui.session import Session

    path = write_template(tmp_path)
    s = Session(path)
    ProjectSync(path).set_keys({"calibration.path": "/somewhere/cal.toml"})  # e.g. `fieldtool calibrate --project`
    s.project.video.start_s = 2.5  # a keystroke in the TUI
    s.save()
    p = load_project(path)
    assert p.calibration.path == "/somewhere/cal.toml" and p.video.start_s == 2.5
    assert s.project.calibration.path == "/somewhere/cal.toml"  # the session sees it too
    s.project.section.n_sub = 9
    s.save()
    assert load_project(path).calibration.path == "/somewhere/cal.toml"


def test_atomic_write_keeps_links_and_devices(tmp_path):
    """A rename would replace a link (e.g. /dev/stdout) or a device by a plain file."""
    import os

    from fieldtool.project.model import atomic_write_bytes

    target = tmp_path / "real.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    atomic_write_bytes(link, b"new")
    assert link.is_symlink() and target.read_bytes() == b"new"
    atomic_write_bytes(Path("/dev/null"), b"x")
    assert Path("/dev/null").is_char_device()
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    r = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    try:
        atomic_write_bytes(fifo, b"through")
        assert os.read(r, 100) == b"through" and fifo.is_fifo()
    finally:
        os.close(r)
