"""The explorer: a design's histories and peaks, live, in a notebook or a browser
(`explorer`).

May import: `_files`, `_figures`."""

__all__: list[str] = []
