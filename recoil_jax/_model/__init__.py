"""The model and its solver, one concept a module:

- `registry`: the registry's types (`Parameter`, `Limits`), `ParameterError`, and the
  validation of a value against its limits;
- `parameter_table`: the registry's data, every design parameter (`PARAMETERS`);
- `params`: the design (`RecoilParams`, one of each part) and the flat names;
- `settings`: the smoothing widths, the solver options, a design's end time and the
  check that its load fits;
- `text_files`: the one reader of text files (`read_text`, `MAX_TEXT_BYTES`);
- `metrics`: the metric registry (`METRICS`) and the containers of metrics by name;
- `forces/`: the forces family (`Part`, `Force`): one module per part of the gun, its
  parameters and its laws, and their sum (`forces.system`);
- `equations`: the equations of motion as a diffrax term, its arguments, the initial
  state and the tracked signals; `rest`: the gun at rest before the shot; `bounds`: what
  a solve can still reach, which lets it stop early;
- `stepping`, `dense`, `lanes`, `solve`: the step loop with its peaks and events, the
  maxima between steps, the lane scheduler, and solving one design or a batch;
- `status`: how a solve ended (`Status`);
- `derivatives`: the forward sensitivities (tangents) of peaks and signals;
- `smooth_max`: the smooth maxima and metric series a gradient solve integrates;
- `differentiable`: differentiable peaks;
- `programs`: the compiled-program cache;
- `feasibility`: the one feasibility rule;
- `paper`, `reference`: the paper's cases and the independent hard-switch reference
  solver.

May import: nothing else of the package (the bottom layer)."""
