"""The model and its solver: the parameters and their registry (`params`), the equations
of motion and the recoil hardware (`equations`), the step loop with its peaks and events
(`stepping`, `dense`, `lanes`, `solve`), the status codes, the metrics, the forward
sensitivities of peaks and signals (`derivatives`), differentiable peaks
(`differentiable`), the compiled-program cache (`programs`), the paper's cases and the
independent hard-switch reference solver (`reference`).

May import: nothing else of the package (the bottom layer)."""
