"""Global sensitivity analysis (Sobol, Morris, DGSM) of a design's metrics over a box of
tolerances, solved through the sweep (`analysis`). Not the forward sensitivities, which
are `_model.derivatives`.

May import: `_model`, `_campaigns`, `_sweeps`, `_design` (only its problem's objective)."""
