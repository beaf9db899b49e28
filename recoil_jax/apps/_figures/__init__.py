"""Every figure the applications draw (matplotlib draws here and nowhere else):
histories and series, sweep maps, optimisation convergence and fronts, calibration fits,
profiles and predictions, sensitivity indices, the paper's figures.

May import: `_files`."""

import matplotlib

# Before any of this folder's modules imports pyplot: figures are files, no display needed.
matplotlib.use("Agg")

__all__: list[str] = []
