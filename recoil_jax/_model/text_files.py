"""The one reader of text files: every file the command line reads (a trace, a force
table, a TOML file, a points file, a calibration's result) comes through `read_text`,
which refuses what is not a regular text file of at most `MAX_TEXT_BYTES`; and the one
way a file is written whole or not at all (`written`)."""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from .._model.registry import ParameterError

__all__ = ["MAX_TEXT_BYTES", "read_text", "written"]


#: The most bytes a text file may hold (a trace, a force table, a TOML file, a points
#: file, a calibration's result): 64 MiB, about 3 million rows of a two-signal trace,
#: which read in about 1 GB. A larger file is refused before it is read.
MAX_TEXT_BYTES = 64 * 2**20


def read_text(path, what: str) -> str:
    """The text of the file `path` (`what` it should be, for messages): a missing file, a
    folder, what is not a regular file (a pipe, a device: it could be read forever), a
    file of more than `MAX_TEXT_BYTES` or one that is not text is a `ParameterError`; a
    byte-order mark (as spreadsheets write) is dropped. Every file the command line reads
    comes through here."""
    path = Path(path)
    try:
        # Non-blocking: opening a pipe with no writer would otherwise wait forever.
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise ParameterError(f"{what} {path} not found") from None
    except IsADirectoryError:
        raise ParameterError(f"{what} {path} is a folder, not a file") from None
    except OSError as error:
        raise ParameterError(f"{what} {path} cannot be read: {error.strerror}") from None
    status = os.fstat(descriptor)
    mode = status.st_mode
    if not stat.S_ISREG(mode):
        os.close(descriptor)
        if stat.S_ISDIR(mode):
            raise ParameterError(f"{what} {path} is a folder, not a file")
        raise ParameterError(
            f"{what} {path} is not a regular file (a pipe, a device or a socket): give a file"
        )
    too_large = ParameterError(
        f"{what} {path} is larger than {MAX_TEXT_BYTES / 2**20:g} MiB, the most a file "
        "read whole may hold (MAX_TEXT_BYTES): give a shorter file (a trace: fewer "
        "samples, e.g. every n-th row)"
    )
    if status.st_size > MAX_TEXT_BYTES:  # refused before a byte is read
        os.close(descriptor)
        raise too_large
    with os.fdopen(descriptor, "rb") as file:
        try:
            data = file.read(MAX_TEXT_BYTES + 1)  # a file that grows as it is read
        except OSError as error:
            raise ParameterError(f"{what} {path} cannot be read: {error.strerror}") from None
    if len(data) > MAX_TEXT_BYTES:
        raise too_large
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ParameterError(f"{what} {path} is not a text file (UTF-8)") from None


@contextlib.contextmanager
def written(path) -> Iterator[Path]:
    """Write the file `path` whole or not at all: yields a temporary path beside it to
    write, renamed over `path` once the block ends; on any failure the temporary file is
    removed (a full disk leaves no truncated or empty file), and an `OSError` naming no
    file, or the temporary one, is raised again naming `path` (what was being written)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        yield temporary
        os.replace(temporary, path)
    except BaseException as error:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        if isinstance(error, OSError) and error.filename in (None, "", str(temporary)):
            raise OSError(error.errno, error.strerror, str(path)) from None
        raise
