"""The `recoil-jax` command's entry point (pyproject's `[project.scripts]`): it runs
`recoil_jax.apps._cli.parser.main` (the same arguments, the same exit status) inside what only
a process can do, before the heavy imports (JAX takes about a second):

- Ctrl-C at any moment, the imports included, ends with one line and status 130, never
  a traceback; after the first (and once the command is done), further Ctrl-C are
  ignored while the process shuts down (an interrupted `atexit` hook, or a C++ thread,
  would print a traceback or abort).
- A standard output or error closed by the caller (`recoil-jax ... >&-`) is pointed at
  /dev/null, so that no file the command opens takes its descriptor and prints do not
  fail.

It lives outside the `recoil_jax` package on purpose: importing anything inside it
imports JAX first.
"""

from __future__ import annotations

import os
import signal
import sys
import time

__all__ = ["main"]

#: The exit status after Ctrl-C (the shell's 128 + SIGINT), as `recoil_jax.apps._cli.boundary`.
INTERRUPTED = 130

#: Seconds after a first Ctrl-C during which further ones are ignored: the command is
#: stopping (a sweep waits for the designs its threads are solving; leaving them
#: running at exit aborts the process). A Ctrl-C after that stops it again.
SHUTDOWN_GRACE_S = 30.0

_first: list[float] = []  # when the first Ctrl-C came


def _interrupt(signum, frame) -> None:
    """Ctrl-C during the command: KeyboardInterrupt, which the command's boundary reports;
    the next ones within `SHUTDOWN_GRACE_S` are ignored."""
    now = time.monotonic()
    if _first and now - _first[-1] < SHUTDOWN_GRACE_S:
        return
    _first.append(now)
    raise KeyboardInterrupt


def _while_starting(signum, frame) -> None:
    """Ctrl-C during the imports: nothing has been done yet, so nothing to clean up; exit
    at once (raising KeyboardInterrupt there could land in an extension's initialisation
    or a garbage-collector callback, which prints it and goes on)."""
    os.write(2, b"recoil-jax: interrupted while starting; nothing was done\n")
    os._exit(INTERRUPTED)


def _reopen_closed_streams() -> None:
    for descriptor, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        try:
            os.fstat(descriptor)
        except OSError:  # closed: take its number with /dev/null
            opened = os.open(os.devnull, os.O_RDONLY if descriptor == 0 else os.O_WRONLY)
            if opened != descriptor:
                os.dup2(opened, descriptor)
                os.close(opened)
        if getattr(sys, name) is None:
            setattr(sys, name, open(descriptor, "r" if descriptor == 0 else "w", closefd=False))


def main() -> int:
    """Run the command line with `sys.argv[1:]`; its exit status."""
    handled = signal.getsignal(signal.SIGINT) is signal.default_int_handler  # not ignored
    if handled:
        signal.signal(signal.SIGINT, _while_starting)
    _reopen_closed_streams()
    from recoil_jax.apps import _cli

    if handled:  # the command: Ctrl-C is KeyboardInterrupt, reported at its boundary
        signal.signal(signal.SIGINT, _interrupt)
    try:
        status = _cli.main()
    except KeyboardInterrupt:  # outside the command's boundary (parsing its arguments)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("recoil-jax: interrupted; nothing was kept", file=sys.stderr)
        return INTERRUPTED
    if handled:  # shutting down: a Ctrl-C now would interrupt atexit hooks or threads
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return status


if __name__ == "__main__":
    sys.exit(main())
