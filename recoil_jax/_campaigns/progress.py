"""Progress: a line on stderr for long work (sweeps, optimisation runs, calibrations:
`Progress`), and where a campaign stands, read from its store while it runs or after
(`campaign_progress`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._model.feasibility import best_feasible_note
from .._model.registry import ParameterError
from .store import connect_read, read_meta

__all__ = ["CampaignProgress", "Progress", "campaign_progress"]


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


class CampaignProgress(NamedTuple):
    """Where a campaign stands, read from its store (`campaign_progress`).

    - `kind`: `"sweep"`, `"study"` or `"calibration"`;
    - `total`, `done`: a sweep's designs, and those committed; a study's planned
      evaluations (a rough guide: a local run may take more or fewer) and those made;
      a calibration's fits (its starts, and its profiles' points) and those committed;
    - `runs`: how many times it was started or resumed;
    - `rate`: designs (evaluations) per second over the latest run (NaN before that
      run's first commit);
    - `seconds_left`: what is still to do at that rate (NaN if unknown; 0 when done; a
      study's by its plan, as rough);
    - `best`: a study's best feasible objective so far (NaN if none; a sweep: NaN).
    """

    kind: str
    total: int
    done: int
    runs: int
    rate: float
    seconds_left: float
    best: float = float("nan")

    def line(self) -> str:
        """One line: done/total, rate, time left (a study: its best so far)."""
        runs = f"{self.runs} run{'s' * (self.runs != 1)}"
        if self.kind == "study":
            text = f"study: {self.done} evaluations, {runs}, {best_feasible_note(self.best)}"
            if np.isfinite(self.rate):
                text += f", {self.rate:.1f}/s in the latest run"
            return text
        share = self.done / self.total if self.total else 1.0
        unit = "fits" if self.kind == "calibration" else "designs"
        text = f"{self.kind}: {self.done}/{self.total} {unit} ({100 * share:.1f} %), {runs}"
        if self.done >= self.total:
            return text + ", finished"
        if np.isfinite(self.rate):
            text += f", {self.rate:.0f}/s in the latest run, ~{self.seconds_left:.0f} s left"
        return text


def campaign_progress(path) -> CampaignProgress:
    """Where the campaign whose store is `path` stands (`CampaignProgress`), read while it
    runs (from another process) or after it stopped. Raises `ParameterError` for a
    missing file or one that is not a store."""
    db = connect_read(Path(path))
    best = float("nan")
    try:
        meta = read_meta(db)
        if not meta:
            raise ParameterError(f"store {path} is empty: not a recoil-jax store")
        total = int(meta["total"])
        runs, run, started = db.execute(
            "SELECT COUNT(*), MAX(run), MAX(started) FROM runs"
        ).fetchone()
        if meta["kind"] == "study":
            done, low = db.execute(
                "SELECT COUNT(*), MIN(CASE WHEN feasible THEN objective END) FROM evaluations"
            ).fetchone()
            best = float("nan") if low is None else float(low)
            # The latest run's rate over its own stretch of the time budget.
            made, first, last = db.execute(
                "SELECT COUNT(*), MIN(seconds), MAX(seconds) FROM evaluations WHERE run = ?",
                (run,),
            ).fetchone()
            span = (last - first) if made and last is not None else 0.0
        else:
            done = db.execute("SELECT COALESCE(SUM(designs), 0) FROM chunks").fetchone()[0]
            made, last = db.execute(
                "SELECT COALESCE(SUM(designs), 0), MAX(finished) FROM chunks WHERE run = ?",
                (run,),
            ).fetchone()
            span = (last - started) if made and last else 0.0
    finally:
        db.close()
    rate = made / span if span > 0 else float("nan")
    left = 0.0 if done >= total else (total - done) / rate if np.isfinite(rate) else float("nan")
    return CampaignProgress(
        meta["kind"], total, int(done), int(runs), float(rate), float(left), best
    )
