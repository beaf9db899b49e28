"""Calibration: measured traces and experiments (`traces`), the fit and its report
(`calibrate`), the test of whether the model explains the traces (`model_check`), and
predictions from a fit's uncertainty (`predict`).

May import: `_model`, `_campaigns`, `_sweeps`, and `_design.evaluators` for the search
space (until it moves to `_sweeps`); never the optimiser."""
