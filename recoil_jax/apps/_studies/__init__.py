"""The studies a file describes: an optimisation study read and checked (`study_file`),
run through `rj.search` or `rj.optimise` and reported (`study`), its best design checked
(`checks`); a global sensitivity analysis's file read and checked (`sensitivity_file`);
a test plan's file (`plan_file`).

May import: `_files`, `_figures`."""

__all__: list[str] = []
