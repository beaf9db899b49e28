"""Calibration: fitting the model's parameters to measured firing traces, judging the fit,
and predicting from it. One module a concept:

- `traces`: measured traces (`read_trace`, `Trace`) and what is known of each firing
  (`Experiment`);
- `spec`: the problem as given, checked when made (`Calibration`);
- `layout`: where each fitted value goes (`Layout`) and the arrays a fit runs on
  (`prepare`);
- `least_squares`: the residuals, Levenberg–Marquardt on exact sensitivities, and the
  compiled fit programs;
- `starts`: where the fits start (the given start, Sobol points);
- `result`: what a calibration gives (`Fitted`, `CalibrationResult`);
- `report`: the report at the optimum: χ², covariance, identifiability, the model check;
- `profiles`: profile-likelihood intervals;
- `campaign`: a calibration kept in a store, so that a killed one resumes;
- `calibrate`: the entry points (`calibrate`, `validate`, `fit_many`);
- `model_check`: does the model explain the traces (`ModelCheck`);
- `posterior`: the posterior by NUTS on the fit's likelihood (`sample_posterior`);
- `predict`: the fitted parameters' uncertainty (`FittedParameters`) and any design's
  peaks with a band from it (`predict`).

May import: `_model`, `_campaigns`, `_sweeps` (the batches and the search space); never
`_design`, the optimiser."""
