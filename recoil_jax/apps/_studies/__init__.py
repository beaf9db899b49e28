"""The optimisation studies: a study file read and checked, run through `rj.search` or
`rj.optimise`, its best design checked and reported (`study`).

May import: `_files`, `_figures`."""

__all__: list[str] = []
