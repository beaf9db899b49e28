"""Make the stores `tests/test_store.py::test_stores_made_before_the_redraw_resume` reads:
a sweep's, a search's, an optimisation's and a calibration's, each small and finished.
They were made at 66a0bae, before issue 53 redrew the package, and made again when
issue 54 changed every campaign's identity on purpose (the design's structure gained
the firing envelope's groups, the smoothing its widths, the results their columns, a
design problem its firing conditions), and again for the firing envelope's revision 2
(issue 62: a store's `model` revision; `sweep_revision1.sqlite` is the sweep's store as
it was before, kept to show that such a store is refused), and the calibration's alone
for issue 63 (the fit's third stopping test, a field of its settings, is in every
calibration store's identity), and the calibration's again at d4bfe79 (issue 65) from a
trace kept as numbers (`calibration_trace.csv`: the simulated one's last bits, and so its
store's identity, differed between CPUs), and all four again for the model's revision 3
(issue 66: the stick a mode, the friction's smoothing widths gone from every identity;
`sweep_revision2.sqlite` is the sweep's store as it was before, refused), and the
calibration's again when its fits left out the samples beside a jump (`jump_passes`, a
field of its settings), and the calibration's again when its identity came to hold what
it was given instead of what it computed from it (a noise guessed from a trace, the
starts' box coordinates: their last bits differ between CPUs, and the store made on one
machine was refused on another), with

    PYTHONPATH=<a checkout of 66a0bae> python tests/data/stores/make_stores.py tests/data/stores

A store's identity holds the package's version: a release refuses older stores on
purpose, and then these are made again with this script."""

import sys
from pathlib import Path

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

#: The designs of the sweep: 2 chunks of 4.
SWEEP = {"m": np.array([0.0, 500.0, 800.0, 1500.0] * 2), "gap": np.repeat([0.03, 0.06], 4)}
SWEEP_PLAN = dict(chunk_size=4, workers=1)
SEARCH = dict(global_phase=rj.SobolStarts(8, 1), workers=1)
OPTIMISE = dict(starts=2, steps=6)
TRUTH = {"k": 28000.0, "c_out": 6000.0, "v0": 0.69}


def gap_problem() -> rj.DesignProblem:
    return rj.DesignProblem(
        params=rj.params_from_values(m=1500.0, gap=0.05),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap",),
        bounds={"gap": (0.0, 0.12)},
        constraints=(rj.Constraint("max_stroke", upper=0.15),),
    )


def calibration() -> rj.Calibration:
    """k and c_out fitted to a noisy firing: `calibration_trace.csv`, the truth `TRUTH`
    (m = 0) simulated at 301 times with normal noise drawn with a fixed seed, kept as
    numbers because a simulation's last bits differ between CPUs (the store's identity
    holds its trace's, bit for bit)."""
    ts, x_M, F_AN = np.loadtxt(Path(__file__).parent / "calibration_trace.csv", delimiter=",").T
    trace = rjx.Trace.of(ts, x_M=x_M, F_AN=F_AN)
    return rj.Calibration(
        [rjx.Experiment(trace)],
        fit={"k": (1e4, 1e5), "c_out": (1e3, 3e4)},
        design={"m": 0.0, "v0": 0.69},
    )


def main(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("sweep", "search", "optimise", "calibration"):
        (folder / f"{name}.sqlite").unlink(missing_ok=True)
    rj.sweep(SWEEP, store=folder / "sweep.sqlite", progress=False, **SWEEP_PLAN)
    rj.search(gap_problem(), store=folder / "search.sqlite", progress=False, **SEARCH)
    rj.optimise(gap_problem(), store=folder / "optimise.sqlite", progress=False, **OPTIMISE)
    rj.calibrate(calibration(), starts=2, store=folder / "calibration.sqlite", progress=False)
    for path in sorted(folder.glob("*.sqlite")):
        print(f"{path}: {path.stat().st_size} bytes")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
