"""The command line's fault boundary: where what the outside world does to a run (bad
input, a failed solve, a missing extra, Ctrl-C, a closed pipe, a full or read-only
disk, a damaged store) becomes one line on stderr and a documented exit status
(`run_command`). Anything else is a bug, and keeps its traceback. What a process can do
before the heavy imports (Ctrl-C while starting, closed streams) is in the entry module,
`recoil_jax_entry.py`."""

from __future__ import annotations

import contextlib
import errno
import io
import os
import select
import sqlite3
import sys

import recoil_jax as rj

__all__ = ["INTERRUPTED", "OPTIONAL", "run_command"]

#: The modules of the optional extras (pyproject.toml): what needs each, and its extra.
OPTIONAL = {
    "panel": ("the design explorer", "apps"),
    "bokeh": ("the design explorer", "apps"),
    "cmaes": ("CMA-ES, for bench-tuning", "apps"),
    "distributed": ("Dask, for --workers and --scheduler", "apps"),
    "blackjax": ("NUTS, for --posterior", "posterior"),
    "arviz": ("ArviZ, for --posterior", "posterior"),
}

#: The exit status after Ctrl-C (the shell's 128 + SIGINT).
INTERRUPTED = 130

#: What the file system can do to a run that is not a bug of ours: full, read-only, not
#: permitted, a broken device.
_ENVIRONMENT_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                       errno.EIO}  # fmt: skip
#: SQLite's messages for the same faults, on a store.
_SQLITE_ENVIRONMENT = ("database or disk is full", "readonly database", "unable to open",
                       "disk I/O error")  # fmt: skip
#: SQLite's messages for a store whose file is damaged (garbage bytes, cut short).
_SQLITE_DAMAGED = ("malformed", "not a database", "corrupt")


def run_command(args) -> int:
    """The command, inside the one boundary where what the outside world does to a run
    (bad input, a failed solve, a missing extra, Ctrl-C, a closed pipe, a full or
    read-only disk) becomes one line on stderr and a documented status. Anything else
    is a bug, and keeps its traceback."""
    try:
        with _marked_stdout():
            status = args.func(args)
    except rj.ParameterError as error:
        print(f"recoil-jax: error: {error}", file=sys.stderr)
        return 2
    except rj.SolveError as error:
        print(f"recoil-jax: solver failed: {rj.failure_message(error)}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as error:
        if error.name not in OPTIONAL:
            raise
        what, extra = OPTIONAL[error.name]
        print(
            f"recoil-jax: error: {args.command} needs {error.name} ({what}), "
            f"which the core install leaves out: pip install 'recoil-jax[{extra}]'",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print(f"recoil-jax: interrupted; {_kept(args)}", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError as error:
        if _stdout_closed():
            return 1  # the reader went away (`| head`): nothing more to say, to anyone
        print(f"recoil-jax: error: a pipe closed: {error}", file=sys.stderr)
        return 1
    except StandardOutputError as error:  # `--json > /dev/full`: not the output folder
        print(f"recoil-jax: error: cannot write standard output: {error.strerror}",
              file=sys.stderr)  # fmt: skip
        with contextlib.suppress(OSError, ValueError):
            sys.stdout = open(os.devnull, "w")  # what it holds cannot be written, at exit
        return 1
    except OSError as error:
        if error.errno not in _ENVIRONMENT_ERRORS:
            raise
        # A write that failed inside a library (no file name) was into the output folder.
        out = getattr(args, "out", None)
        where = (
            f"{error.filename}: " if error.filename else (f"writing into {out}: " if out else "")
        )
        print(f"recoil-jax: error: {where}{error.strerror}", file=sys.stderr)
        return 1
    except sqlite3.DatabaseError as error:  # OperationalError is one too
        store = getattr(args, "store", None)
        if any(text in str(error) for text in _SQLITE_DAMAGED) and store:
            print(f"recoil-jax: error: store {store} is damaged ({error}): move it aside to "
                  "keep it, or delete it to start again", file=sys.stderr)  # fmt: skip
            return 2
        if not (isinstance(error, sqlite3.OperationalError) and
                any(text in str(error) for text in _SQLITE_ENVIRONMENT)):  # fmt: skip
            raise
        where = f"store {store}: " if store else ""
        print(f"recoil-jax: error: {where}{error}", file=sys.stderr)
        return 1
    if sys.stdout is None:  # closed before the start (`recoil-jax ... >&-`)
        return status
    try:  # a full disk or a closed pipe on stdout shows here, not at exit
        sys.stdout.flush()
    except BrokenPipeError:
        if not _stdout_closed():
            print("recoil-jax: error: standard output closed", file=sys.stderr)
        return 1
    except OSError as error:
        print(f"recoil-jax: error: cannot write standard output: {error.strerror}",
              file=sys.stderr)  # fmt: skip
        return 1
    return status


class StandardOutputError(OSError):
    """A write to standard output that failed (a full device), told apart from a write
    into the output folder."""


class _Marked:
    """Standard output whose failed writes are `StandardOutputError`s (a closed pipe
    stays a `BrokenPipeError`); everything else (`fileno`, `isatty`, `encoding`, `buffer`)
    is the stream's own."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            raise
        except OSError as error:
            raise StandardOutputError(error.errno, error.strerror) from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise
        except OSError as error:
            raise StandardOutputError(error.errno, error.strerror) from None

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _marked_stdout():
    """Standard output marked (`_Marked`) while a command runs."""
    stream = sys.stdout
    if stream is None:
        yield
        return
    sys.stdout = _Marked(stream)
    try:
        yield
    finally:
        if isinstance(sys.stdout, _Marked):
            sys.stdout = stream


def _stdout_closed() -> bool:
    """Whether stdout's reader has gone (a pipe whose reading end is closed reports an
    error to `poll`): if so, point stdout at /dev/null, so that the interpreter's own
    flush at exit does not fail again."""
    try:
        descriptor = sys.stdout.fileno()
        watch = select.poll()
        watch.register(descriptor, select.POLLOUT)
        closed = any(event & select.POLLERR for _, event in watch.poll(0))
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        return False  # not a file (a notebook, a test's capture): not a closed pipe
    if not closed:
        return False
    with contextlib.suppress(OSError, ValueError, io.UnsupportedOperation):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    return True


def _kept(args) -> str:
    """What an interrupted command kept, and how to go on."""
    store = getattr(args, "store", None) if args.command != "progress" else None
    if store:
        return (f"every finished part is in {store}: run the same command with --store "
                f"{store} to resume")  # fmt: skip
    if args.command in ("sweep", "optimise", "sensitivity", "calibrate"):
        return "nothing was kept (give --store FILE.sqlite to make a run resumable)"
    return "nothing was kept"
