"""A progress line on stderr for long work (sweeps, optimisation runs)."""

from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


class Progress:
    """`label [#####.....] done/total unit, elapsed, rate, time left, note`: redrawn in
    place on a terminal, else printed at most every tenth of the way and at the end.
    `enabled=None`: only on a terminal. `already`: work done before this run (a resumed
    campaign), counted as done but not in the rate. `rates=False`: no rate and no time
    left (steps of unequal length, as a calibration's phases)."""

    def __init__(
        self,
        label: str,
        total: int,
        unit: str,
        enabled: bool | None,
        stream=None,
        already: int = 0,
        rates: bool = True,
    ):
        self.label, self.total, self.unit = label, total, unit
        self.already = self.done = already
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.enabled = self.tty if enabled is None else enabled
        self._printed = already
        self.rates = rates

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def update(self, done: int, note: str = "", final: bool = False) -> None:
        self.done = done
        if not self.enabled:
            return
        final = final or done >= self.total
        step = max(1, self.total // 10)
        if not (self.tty or final or done - self._printed >= step):
            return
        self._printed = done
        elapsed = self.elapsed
        rate = (done - self.already) / elapsed if elapsed > 0 else 0.0
        left = (self.total - done) / rate if rate > 0 and not final else 0.0
        width = 30
        filled = int(width * min(done, self.total) / self.total)
        line = (
            f"{self.label} [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} "
            f"{self.unit}, {elapsed:.1f} s"
            + (f", {rate:.0f}/s" if self.rates else "")
            + ("" if final or not self.rates else f", ~{left:.0f} s left")
            + (f", {note}" if note else "")
        )
        print(line, end="\r" if self.tty and not final else "\n", file=self.stream, flush=True)
