"""The top-level guard: exit 1 one line for an internal error (traceback only with --debug), exit 2
naming the path for an OSError, encodings of the project file, the progress line never glued."""

import errno

import pytest

from fieldtool.cli import main as cli


def _boom_with(exc):
    def boom(args):
        raise exc

    return boom


@pytest.fixture()
def patched_init(monkeypatch):
    def set_exc(exc):
        monkeypatch.setattr(cli, "cmd_init", _boom_with(exc))

    return set_exc


def test_internal_error_is_one_line_exit_1(patched_init, capsys):
    patched_init(TypeError("unsupported operand"))
    assert cli.main(["init", "x"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error: TypeError" in err and "report" in err
    assert "Traceback" not in err


def test_debug_shows_the_traceback(patched_init):
    patched_init(TypeError("unsupported operand"))
    with pytest.raises(TypeError):
        cli.main(["--debug", "init", "x"])


@pytest.mark.parametrize(
    "code,word",
    [
        (errno.ENOSPC, "free some space"),
        (errno.EACCES, "permission"),
        (errno.ENOTDIR, "not a folder"),
        (errno.EROFS, "read-only"),
    ],
)
def test_os_errors_exit_2_naming_the_path(patched_init, capsys, code, word):
    patched_init(OSError(code, "system text", "/data/out/result.json"))
    assert cli.main(["init", "x"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/data/out/result.json" in err and word in err


def test_progress_line_ends_before_an_error(capsys, monkeypatch):
    from fieldtool.cli.console import progress_line
    from fieldtool.errors import InputFileError

    def cmd(args):
        progress_line("frames searched: 36/36")
        raise InputFileError("board.mkv: no checkerboard found")

    monkeypatch.setattr(cli, "cmd_init", cmd)
    assert cli.main(["init", "x"]) == 2
    err = capsys.readouterr().err
    assert "36/36\nfieldtool: error: board.mkv" in err


@pytest.mark.parametrize("encoding", ["latin-1", "utf-16", "utf-8-sig"])
def test_project_file_in_other_encodings(short_scene, tmp_path, encoding, capsys):
    import shutil

    for p in (short_scene.video_path, short_scene.cross_section_path):
        shutil.copy(p, tmp_path / p.name)
    text = short_scene.project_path.read_text(encoding="utf-8").replace(
        'name = "synthetic oblique"', 'name = "Mesure à l\'écluse"'
    )
    (tmp_path / "project.toml").write_bytes(text.encode(encoding))
    from fieldtool.project.model import load_project

    assert load_project(tmp_path / "project.toml").name == "Mesure à l'écluse"
    assert cli.main(["preview", str(tmp_path / "project.toml"), "--out", str(tmp_path / "p.png")]) == 0
    err = capsys.readouterr().err
    assert ("read as cp1252" in err) == (encoding == "latin-1")


def test_binary_project_refused(tmp_path, capsys):
    (tmp_path / "project.toml").write_bytes(bytes(range(256)) * 4)
    assert cli.main(["run", str(tmp_path / "project.toml")]) == 2
    assert "not a text file" in capsys.readouterr().err


def test_levels_file_encodings_and_delimiters(tmp_path):
    import warnings

    from fieldtool.errors import FieldToolWarning, InputFileError
    from fieldtool.records.batch import read_levels

    p = tmp_path / "levels.csv"
    p.write_bytes("video;water_level_m\nclip é.mp4;1,5\n".encode("latin-1"))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert read_levels(p)["clip é.mp4"] == 1.5
    assert any(issubclass(x.category, FieldToolWarning) and "cp1252" in str(x.message) for x in w)
    p.write_bytes(b"videowaterlevel\nabc\n")
    with pytest.raises(InputFileError, match="no ',' ';' or tab"):
        read_levels(p)
    p.write_bytes(bytes(range(256)))
    with pytest.raises(InputFileError, match="not a text file"):
        read_levels(p)
    p.write_text("video,water_level_m\na.mp4,nan\n")
    with pytest.raises(InputFileError, match="line 2"):
        read_levels(p)


def test_progress_is_written_at_most_every_tenth_of_a_second_and_its_last_count(capsys, monkeypatch):
    """The run's stages report every frame; on a terminal the line is rewritten at most every TTY_EVERY_S within a
    stage, and at once for a new stage; the last count is written when the line ends. An update too soon does not
    even ask stderr whether it is a terminal (a system call, on the decoding thread)."""
    from fieldtool.cli import console, measure

    clock = [100.0]
    asked = []
    monkeypatch.setattr(console.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(console, "_is_tty", lambda: asked.append(1) or True)
    monkeypatch.setattr(console, "_state", {"open": False, "t": 0.0, "stage": None, "pending": None})
    for k in range(1, 241):  # 240 frames in 0.24 s
        measure._print_progress("frames", k, 240)
        clock[0] += 0.001
    frames = [s for s in capsys.readouterr().err.split("\r") if s.strip()]
    assert frames[0].strip() == "frames: 1/240" and len(frames) <= 3 and len(asked) <= 3
    measure._print_progress("pairs", 1, 30)  # a new stage at once
    clock[0] += 0.001
    measure._print_progress("pairs", 2, 30)  # too soon: remembered
    console.end_progress_line()
    written = [s for s in capsys.readouterr().err.split("\r") if s.strip()]
    assert [s.strip() for s in written] == ["pairs: 1/30", "pairs: 2/30"]  # the last count, when the line ends
