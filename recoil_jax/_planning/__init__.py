"""Planning a firing test: the Fisher information of candidate firings from the exact
signal sensitivities (`information`), the problem as given (`problem`), the choice of
firings and signals (`choose`: greedy, Fedorov exchange, exhaustive), the plan and what
it predicts against hand-drawn plans (`plan`), and the check of the prediction by
simulated, fitted tests (`check`).

May import: `_model`, `_sweeps`, `_calibration`."""
