"""The output folder as a unit (issue 25): never beside or over an input, a kept symbolic link, a refused read-only
folder, a full disk, SIGINT/SIGTERM/kill -9 at any moment, stale temporary folders, two runs into one folder.

The kill test here is bounded (5 seeded moments); benchmarks/kill_outputs.py runs 30.
"""

import errno
import os
import random
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import tomli_w
from outputs_harness import kill_once, snapshot, temp_leftovers, time_phases, verdict

from fieldtool.cli.main import main

HARNESS = Path(__file__).resolve().parents[1] / "outputs_harness.py"


def _project(scene_dir: Path, edit=None, name="project.toml") -> Path:
    data = tomllib.loads((scene_dir / "project.toml").read_text())
    if edit:
        edit(data)
    p = scene_dir / name
    p.write_text(tomli_w.dumps(data))
    return p


def _new_settings(d):
    """The second run: other subsections and other PIV windows (a new PIV field, so a new piv_cache.npz)."""
    d["section"]["n_sub"] = 7
    d["piv"]["window_px"] = 24


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def _child(*argv, frame_delay=0.0, write_delay=0.0, **kw):
    return subprocess.Popen(
        [sys.executable, str(HARNESS), str(frame_delay), str(write_delay), *map(str, argv)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        **kw,
    )


def _wait_for(cond, proc, limit=120.0):
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() - t0 < limit
        time.sleep(0.02)


def _staging(parent: Path) -> list[Path]:
    return [p for p in parent.iterdir() if ".tmp-" in p.name]


# --- never beside or over an input --------------------------------------------------------------


def test_out_set_to_the_project_folder_is_refused(scene, capsys):
    proj = _project(scene)
    (scene / "profile.png").write_bytes(b"the user's own profile")
    (scene / "section.png").write_bytes(b"the user's own section")
    before = snapshot(scene)
    code, _, err = _run(capsys, "run", proj, "--out", scene, "--quiet")
    assert code == 2, err
    assert "project's own folder" in err and err.count("\n") == 1
    assert snapshot(scene) == before  # profile.png and section.png untouched, nothing added


def test_out_above_the_project_folder_is_refused(scene, capsys):
    proj = _project(scene)
    code, _, err = _run(capsys, "run", proj, "--out", scene.parent, "--quiet")
    assert code == 2 and "project's own folder" in err


def test_out_holding_the_image_sequence_is_refused(scene, capsys):
    import cv2

    frames = scene / "frames"
    frames.mkdir()
    cap = cv2.VideoCapture(str(scene / "river.mp4"))
    n = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        cv2.imwrite(str(frames / f"f{n:03d}.png"), img)
        n += 1
    cap.release()

    def edit(d):
        d["video"]["path"] = "frames"
        d["video"]["frame_interval_s"] = 1 / 30

    proj = _project(scene, edit, "seq.toml")
    (scene / "project.toml").unlink()
    listing = sorted(p.name for p in frames.iterdir())
    code, _, err = _run(capsys, "run", proj, "--out", frames, "--quiet")
    assert code == 2, err
    assert "video.path" in err and err.count("\n") == 1
    assert sorted(p.name for p in frames.iterdir()) == listing  # no gcp.png to be read as a frame next time


def test_out_holding_the_cross_section_is_refused(scene, capsys, tmp_path_factory):
    other = tmp_path_factory.mktemp("survey")
    shutil.move(scene / "cross_section.csv", other / "cross_section.csv")
    proj = _project(scene, lambda d: d["cross_section"].update(path=str(other / "cross_section.csv")))
    code, _, err = _run(capsys, "run", proj, "--out", other, "--quiet")
    assert code == 2 and "cross_section.path" in err, err


# --- the folder itself ----------------------------------------------------------------------------


def test_symlinked_out_stays_a_link_and_its_target_is_replaced(scene, capsys):
    proj = _project(scene)
    target = scene / "runs" / "target"
    target.mkdir(parents=True)
    link = scene / "link"
    link.symlink_to(target, target_is_directory=True)
    code, _, err = _run(capsys, "run", proj, "--out", link, "--quiet")
    assert code == 0, err
    assert link.is_symlink() and (target / "result.json").is_file()
    first = (target / "result.json").read_bytes()
    proj = _project(scene, _new_settings)
    code, _, err = _run(capsys, "run", proj, "--out", link, "--quiet")
    assert code == 0, err
    assert link.is_symlink() and Path(os.readlink(link)) == target
    assert (target / "result.json").read_bytes() != first and (target / "subsections.csv").read_text().count("\n") == 8
    assert temp_leftovers(scene) == [] and temp_leftovers(target.parent) == []


def test_read_only_out_is_refused_and_not_swapped(scene, capsys):
    proj = _project(scene)
    out = scene / "out"
    assert _run(capsys, "run", proj, "--out", out, "--quiet")[0] == 0
    before, inode = snapshot(out), out.stat().st_ino
    out.chmod(0o555)
    try:
        proj = _project(scene, _new_settings)
        code, _, err = _run(capsys, "run", proj, "--out", out, "--quiet")
        assert code == 2, err
        assert "read-only" in err and err.count("\n") == 1
        assert out.stat().st_ino == inode and snapshot(out) == before
        assert out.stat().st_mode & 0o777 == 0o555
    finally:
        out.chmod(0o755)
    assert temp_leftovers(scene) == []


def test_full_disk_gives_one_line_and_keeps_the_old_run(scene, capsys, monkeypatch):
    from fieldtool.run import outputs

    proj = _project(scene)
    out = scene / "out"
    assert _run(capsys, "run", proj, "--out", out, "--quiet")[0] == 0
    before = snapshot(out)
    write = outputs.atomic_write_bytes

    def full(path, data):
        if Path(path).name == "mean_field.npy":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write(path, data)

    monkeypatch.setattr(outputs, "atomic_write_bytes", full)
    proj = _project(scene, _new_settings)
    code, _, err = _run(capsys, "run", proj, "--out", out, "--quiet")
    assert code == 2, err
    assert "No space left on device" in err and "free some space" in err and err.count("\n") == 1
    assert snapshot(out) == before
    assert temp_leftovers(scene) == []


def test_interrupted_run_keeps_the_old_piv_cache(scene, capsys, monkeypatch):
    """Ctrl-C after the PIV (while the figures are drawn): the old piv_cache.npz is the old run's, byte for byte."""
    import fieldtool.plots.discharge as plots
    from fieldtool.run import outputs

    proj = _project(scene)
    out = scene / "out"
    assert _run(capsys, "run", proj, "--out", out, "--quiet")[0] == 0
    before = snapshot(out)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "_write_figures", interrupted)
    monkeypatch.setattr(plots, "plot_section", interrupted)
    proj = _project(scene, _new_settings)
    code, _, err = _run(capsys, "run", proj, "--out", out, "--quiet")
    assert code == 130, err
    assert snapshot(out) == before  # piv_cache.npz included
    assert temp_leftovers(scene) == []


def test_stale_temp_folders_of_dead_runs_are_swept(scene, capsys):
    proj = _project(scene)
    out = scene / "out"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for name in (f".out.tmp-{dead.pid}-0badc0de", ".out.tmp-k3x9_q2", f".out.old-{dead.pid}-00000000"):
        (scene / name).mkdir()
        (scene / name / "result.json").write_text("{}")
    (scene / ".out.lock").write_text(f"{dead.pid}\n")
    assert _run(capsys, "run", proj, "--out", out, "--quiet")[0] == 0
    assert temp_leftovers(scene) == []


# --- signals and kills in a child process -----------------------------------------------------------


def test_sigterm_is_a_clean_exit(scene, capsys):
    proj = _project(scene)
    out = scene / "out"
    assert _run(capsys, "run", proj, "--out", out, "--quiet")[0] == 0
    before = snapshot(out)
    proj = _project(scene, _new_settings)
    proc = _child("run", proj, "--out", out, "--quiet", frame_delay=0.2)  # 0.2 s a frame: still in the PIV
    _wait_for(lambda: _staging(scene), proc)  # the run has claimed the folder
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err.decode()
    assert err.decode().strip().splitlines() == ["fieldtool: terminated"], err.decode()
    assert snapshot(out) == before  # piv_cache.npz included
    assert temp_leftovers(scene) == []


def test_a_second_run_into_the_same_folder_is_refused(scene, capsys):
    proj = _project(scene)
    out = scene / "out"
    proc = _child("run", proj, "--out", out, "--quiet", frame_delay=0.1)
    try:
        _wait_for(lambda: _staging(scene), proc)
        code, _, err = _run(capsys, "run", proj, "--out", out, "--quiet")
        assert code == 2, err
        assert "another fieldtool run" in err and str(proc.pid) in err and err.count("\n") == 1
    finally:
        proc.wait(timeout=120)
    assert proc.returncode == 0 and (out / "result.json").is_file()
    assert temp_leftovers(scene) == []


def test_kill_9_at_random_moments_leaves_the_old_run_or_the_new_one(scene, capsys):
    """5 seeded moments (benchmarks/kill_outputs.py: 30): the folder is always one run, byte for byte."""
    proj_old = _project(scene)
    proj_new = _project(scene, _new_settings, "new.toml")
    out = scene / "out"
    assert _run(capsys, "run", proj_old, "--out", out, "--quiet")[0] == 0
    old = snapshot(out)
    kept = scene / "kept"  # the old run's folder as it was, to start again from after a kill that let the new one in
    shutil.copytree(out, kept)

    def start():
        return _child("run", proj_new, "--out", out, "--quiet", frame_delay=0.01, write_delay=0.05)

    timed = scene / "timed"  # the new run over the old one, not killed: its length, and what "new" is byte for byte
    shutil.copytree(out, timed)
    span, write_span = time_phases(
        lambda: _child("run", proj_new, "--out", timed, "--quiet", frame_delay=0.01, write_delay=0.05), scene
    )
    new = snapshot(timed)
    shutil.rmtree(timed)
    rng = random.Random(25)
    seen = []
    for _ in range(5):
        if snapshot(out) != old:  # start again from the old run
            shutil.rmtree(out)
            shutil.copytree(kept, out)
        when = kill_once(start, scene, rng, span, write_span)
        v = verdict(snapshot(out), old, new)
        assert v in ("old", "new"), (when, v)
        seen.append(v)
    assert _run(capsys, "run", proj_new, "--out", out, "--quiet")[0] == 0  # the next run sweeps what the kills left
    assert temp_leftovers(scene) == [], seen
