"""What a command reads and writes, and where it runs: `name=value` items and the files the
commands load (`inputs`), a calibration file read and written (`calibration_file`: the
one home of its keys and limits), the one JSON writer (`json_writer`), a design and a
model in words (`describe`), the Dask cluster a campaign spreads over (`cluster`), and
what every command's parser shares (`options`: `Commands`, through which each command
adds its own parser).

May import: the engine's public API only (`recoil_jax`, `recoil_jax.extend`)."""

__all__: list[str] = []
