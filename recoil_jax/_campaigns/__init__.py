"""Campaigns that resume after a crash: the SQLite stores of sweeps, searches and
calibrations, a campaign's identity, its lock (`store`); a written sweep's store read
back (`sweep_reader`); the one way a campaign opens
its store, says that it resumes and closes it (`opener`); and the progress line and the
reading of a campaign's progress (`progress`).

May import: `_version`, `_model`."""
