"""The optimisation studies: a study file read and checked (`study_file`), run through
`rj.search` or `rj.optimise` and reported (`study`), its best design checked (`checks`).

May import: `_files`, `_figures`."""

__all__: list[str] = []
