"""Text files written by people: project files, level tables and lists, in whatever encoding the
editor used. UTF-8 (with or without BOM) and UTF-16/32 with a BOM are read as such; any other text
is read as Windows-1252 (cp1252, the Windows editors' default for Western languages; Latin-1 where
cp1252 leaves a byte undefined) with a ``FieldToolWarning`` naming the encoding; binary files are
refused with an ``InputFileError`` naming the file."""

from __future__ import annotations

import codecs
import os
import stat
import warnings
from pathlib import Path

from fieldtool.errors import FieldToolWarning, InputFileError

MAX_TEXT_BYTES = 64 * 1024 * 1024  # a project file or a table larger than this is not one

_BOMS = (
    (codecs.BOM_UTF32_LE, "utf-32"),
    (codecs.BOM_UTF32_BE, "utf-32"),
    (codecs.BOM_UTF8, "utf-8-sig"),
    (codecs.BOM_UTF16_LE, "utf-16"),
    (codecs.BOM_UTF16_BE, "utf-16"),
)
_BINARY = set(range(0x00, 0x09)) | {0x0B, 0x0E, 0x0F} | set(range(0x10, 0x1A)) | set(range(0x1C, 0x20)) | {0x7F}


def read_bytes(path: Path | str, what: str) -> bytes:
    """The bytes of a regular file (never opens a pipe or a device; bounded size)."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputFileError(f"{path}: {what} not found") from None
    except OSError as e:
        raise InputFileError(f"{path}: cannot read the {what} ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputFileError(f"{path}: is a folder; give the {what} itself")
    if not stat.S_ISREG(st.st_mode):
        raise InputFileError(f"{path}: is not a regular file (a pipe or a device); give the {what} saved on disk")
    if st.st_size > MAX_TEXT_BYTES:
        raise InputFileError(f"{path}: {st.st_size / 2**20:.0f} MiB is too large for a {what}")
    try:
        return path.read_bytes()
    except OSError as e:
        raise InputFileError(f"{path}: cannot read the {what} ({e.strerror or e})") from None


def decode_text(data: bytes, path: Path | str, what: str) -> tuple[str, str]:
    """(text, encoding) of file bytes; see the module docstring."""
    for bom, enc in _BOMS:
        if data.startswith(bom):
            try:
                return data.decode(enc), enc
            except UnicodeDecodeError:
                raise InputFileError(
                    f"{path}: the {what} starts with a {enc.upper()} mark but is not valid "
                    f"{enc.upper()}; save it again as UTF-8"
                ) from None
    try:
        return data.decode("utf-8"), "utf-8"
    except UnicodeDecodeError:
        pass
    if any(b in _BINARY for b in data[:65536]):
        raise InputFileError(f"{path}: is not a text file (binary content); give the {what} as text (UTF-8)")
    try:
        text, enc = data.decode("cp1252"), "cp1252"
    except UnicodeDecodeError:
        text, enc = data.decode("latin-1"), "latin-1"
    name = "Windows Western" if enc == "cp1252" else "ISO 8859-1"
    warnings.warn(
        FieldToolWarning(
            f"{path}: the {what} is not UTF-8; read as {enc} ({name}); save it as UTF-8 to be sure of accented letters"
        ),
        stacklevel=3,
    )
    return text, enc


def read_text(path: Path | str, what: str) -> str:
    """The text of a file in any encoding fieldtool accepts (see the module docstring)."""
    text, _ = decode_text(read_bytes(path, what), path, what)
    return text
