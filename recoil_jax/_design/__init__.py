"""The optimisation layer: the design problem and its objective and limits (`problem`),
the evaluators (`evaluators`; the search space they move in is `_sweeps.space`), local
methods (`local`), the augmented Lagrangian (`lagrangian`), the global search
(`search`), gradient descent (`optimise`) and their one result (`result`).

May import: `_model`, `_campaigns`, `_sweeps`."""
