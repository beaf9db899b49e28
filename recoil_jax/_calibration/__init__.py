"""Calibration: measured traces and experiments (`traces`), the fit and its report
(`calibrate`), the test of whether the model explains the traces (`model_check`), and
predictions from a fit's uncertainty (`predict`).

May import: `_model`, `_campaigns`, `_sweeps` (the batches and the search space); never
`_design`, the optimiser."""
