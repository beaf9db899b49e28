"""The benchmarks, each a command: throughput against a compiled scalar loop and scipy
(`speed`, with the scalar loop in `anchor`), stores and clusters (`store`), optimisers
(`tuning`), calibration (`calibration`), global sensitivity (`sensitivity`).

May import: `_files`, `_figures`, `_studies`."""

__all__: list[str] = []
