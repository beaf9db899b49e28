"""Campaign stores: a sweep's results committed to an SQLite file chunk by chunk, so that
a run that is killed resumes where it stopped.

SQLite because a store must survive a `kill -9` at any moment and stay readable by
anyone: each chunk is one transaction (all of its rows or none), the file is one
standard database that Python's `sqlite3`, pandas (`read_sql`) or the `sqlite3` shell
read without this project (Optuna and OpenMDAO's case recorder store runs the same way),
and it needs no dependency. The tables:

- `meta` (`key`, `value`): what made the store (`kind`, `identity`, `total`, `plan`,
  `description`, `format`);
- `points`: one row per finished design, in the order they were committed: `point`
  (its index in the sweep's input) and `chunk`, then its parameters by flat name, its
  peaks and gradients (the columns of `sweep.csv`), `status` ("ok" or why the solve
  failed) and `status_code`;
- `chunks` (`chunk`, `designs`, `seconds`, `finished`, `run`): each committed chunk, once;
- `runs` (`run`, `started`, `pid`, `host`): each time the campaign was started or resumed.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import sqlite3
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from ._params import ParameterError

__all__ = ["CampaignProgress", "SweepStore", "campaign_progress", "fingerprint"]

#: The layout of the tables; a store of another format is refused, not misread.
STORE_FORMAT = 1


def fingerprint(*parts: Any) -> str:
    """A SHA-256 digest of pytrees (their structure, static fields included, and every
    leaf's dtype, shape and bytes): equal for equal inputs, bit for bit."""
    digest = hashlib.sha256()
    for part in parts:
        leaves, treedef = jax.tree.flatten(part)
        digest.update(str(treedef).encode())
        for leaf in leaves:
            array = np.ascontiguousarray(np.asarray(leaf))
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _connect(path: Path) -> sqlite3.Connection:
    """An SQLite connection in autocommit mode (transactions are explicit), write-ahead
    logged: a killed writer leaves the last committed transaction intact."""
    if path.is_dir():
        raise ParameterError(f"store {path} is a folder: give the path of a file")
    if not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    try:
        db = sqlite3.connect(path, isolation_level=None, timeout=60.0)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master")}
    except sqlite3.DatabaseError as error:
        raise ParameterError(
            f"store {path} is not a recoil-jax store ({error}): give a new path"
        ) from None
    if tables and "meta" not in tables:
        db.close()
        raise ParameterError(
            f"store {path} is an SQLite file, but not a recoil-jax store: give a new path"
        )
    return db


def _read_meta(db: sqlite3.Connection) -> dict[str, str]:
    tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master")}
    if "meta" not in tables:
        return {}
    return dict(db.execute("SELECT key, value FROM meta").fetchall())


class SweepStore:
    """A sweep's store (see the module's docstring). Opening creates it, or checks that
    it was made by the same sweep (`identity`, a `fingerprint` of everything its results
    depend on) and raises `ParameterError` if not. `plan` (the chunking: workers, lanes,
    chunk size) is kept from the run that made the store, so that a resumed sweep cuts
    the same chunks and gives the same bits."""

    def __init__(
        self,
        path,
        *,
        identity: str,
        total: int,
        plan: dict,
        columns: list[str],
        description: dict,
    ):
        self.path = Path(path)
        self.db = _connect(self.path)
        try:
            meta = _read_meta(self.db)
            if meta:
                self._check(meta, identity)
                self.plan = json.loads(meta["plan"])
                self.columns = json.loads(meta["columns"])
            else:
                self.plan, self.columns = plan, list(columns)
                self._create(identity, total, description)
        except BaseException:
            self.db.close()
            raise
        self.total = total
        cursor = self.db.execute(
            "INSERT INTO runs (started, pid, host) VALUES (?, ?, ?)",
            (time.time(), os.getpid(), socket.gethostname()),
        )
        self.run = cursor.lastrowid

    def _check(self, meta: dict[str, str], identity: str) -> None:
        kind, made = meta.get("kind"), json.loads(meta.get("description", "{}"))
        if kind != "sweep" or meta.get("identity") != identity:
            what = "a study" if kind == "study" else "a different sweep"
            raise ParameterError(
                f"store {self.path} holds the results of {what} ({_describe(made)}), not of "
                "this one: give a new store path, or delete the file to start again"
            )
        if int(meta.get("format", -1)) != STORE_FORMAT:
            raise ParameterError(
                f"store {self.path} was written in store format {meta.get('format')}; this "
                f"version reads format {STORE_FORMAT}: give a new store path"
            )

    def _create(self, identity: str, total: int, description: dict) -> None:
        db = self.db
        data = ", ".join(f"{_quote(name)} REAL" for name in self.columns)
        db.execute("BEGIN IMMEDIATE")
        try:
            db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
            db.execute(
                "CREATE TABLE runs (run INTEGER PRIMARY KEY AUTOINCREMENT, started REAL, "
                "pid INTEGER, host TEXT)"
            )
            db.execute(
                "CREATE TABLE chunks (chunk TEXT PRIMARY KEY, designs INTEGER, seconds REAL, "
                "finished REAL, run INTEGER)"
            )
            # Rows in the order they were committed, `point` not a key: a chunk's points
            # are scattered over the sweep (sorted by gap), and keeping them in a B-tree
            # by point made each commit 4 times slower. Each chunk is written once, in
            # one transaction with its row in `chunks`.
            db.execute(
                f"CREATE TABLE points (point INTEGER, chunk TEXT, {data}, "
                "status TEXT, status_code INTEGER)"
            )
            meta = {
                "kind": "sweep",
                "format": str(STORE_FORMAT),
                "identity": identity,
                "total": str(total),
                "plan": json.dumps(self.plan),
                "columns": json.dumps(self.columns),
                "description": json.dumps(description),
            }
            db.executemany("INSERT INTO meta VALUES (?, ?)", list(meta.items()))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    def done(self) -> dict[str, int]:
        """The committed chunks: key -> number of designs."""
        return dict(self.db.execute("SELECT chunk, designs FROM chunks").fetchall())

    def commit(
        self,
        chunk: str,
        points: np.ndarray,
        data: dict[str, np.ndarray],
        status: list[str],
        seconds: float,
    ) -> bool:
        """Write one chunk's rows (`points`: their indices in the sweep; `data`: a column
        per name of `columns`; `status`: a message per row, "ok" or why) in one
        transaction. A chunk already in the store is left as it is (returns False)."""
        codes = data["status_code"]
        columns = [np.asarray(data[name], dtype=float).tolist() for name in self.columns]
        rows = zip(
            np.asarray(points).tolist(),
            [chunk] * len(points),
            *columns,
            status,
            np.asarray(codes).tolist(),
            strict=True,
        )
        names = ["point", "chunk", *self.columns, "status", "status_code"]
        insert = (
            f"INSERT INTO points ({', '.join(map(_quote, names))}) "
            f"VALUES ({', '.join('?' * len(names))})"
        )
        db = self.db
        db.execute("BEGIN IMMEDIATE")
        try:
            if db.execute("SELECT 1 FROM chunks WHERE chunk = ?", (chunk,)).fetchone():
                db.execute("ROLLBACK")
                return False
            db.executemany(insert, rows)
            db.execute(
                "INSERT INTO chunks VALUES (?, ?, ?, ?, ?)",
                (chunk, len(points), seconds, time.time(), self.run),
            )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        return True

    def read(self, chunks) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The rows of the committed `chunks`: `(points, {column: values})`, in the order
        they were committed; `status_code` as integers, the rest as floats (NULL is NaN)."""
        chunks = list(chunks)
        if not chunks:
            empty = {name: np.zeros(0) for name in self.columns}
            return np.zeros(0, int), empty | {"status_code": np.zeros(0, np.int32)}
        self.db.execute("CREATE TEMP TABLE IF NOT EXISTS wanted (chunk TEXT PRIMARY KEY)")
        self.db.execute("DELETE FROM wanted")
        self.db.executemany("INSERT INTO wanted VALUES (?)", [(c,) for c in chunks])
        names = ["point", *self.columns, "status_code"]
        rows = self.db.execute(
            f"SELECT {', '.join(map(_quote, names))} FROM points "
            "WHERE chunk IN (SELECT chunk FROM wanted)"
        ).fetchall()
        table = np.array(rows, dtype=float).reshape(len(rows), len(names))
        data = {name: table[:, j + 1] for j, name in enumerate(self.columns)}
        data["status_code"] = table[:, -1].astype(np.int32)
        return table[:, 0].astype(int), data

    def close(self) -> None:
        self.db.close()


def _describe(description: dict) -> str:
    parts = [f"{description.get('designs', '?')} designs"]
    if description.get("names"):
        parts.append("of " + ", ".join(description["names"]))
    if description.get("created"):
        parts.append(f"made {description['created']}")
    return ", ".join(parts)


class CampaignProgress(NamedTuple):
    """Where a campaign stands, read from its store (`campaign_progress`).

    - `kind`: `"sweep"`; `total`, `done`: designs in the campaign and committed;
    - `runs`: how many times it was started or resumed;
    - `rate`: designs per second over the latest run (from its start to its last
      commit; NaN before that run's first commit);
    - `seconds_left`: the designs still to do at that rate (NaN if unknown; 0 when done).
    """

    kind: str
    total: int
    done: int
    runs: int
    rate: float
    seconds_left: float

    def line(self) -> str:
        """One line: done/total, rate, time left."""
        share = self.done / self.total if self.total else 1.0
        text = f"{self.kind}: {self.done}/{self.total} designs ({100 * share:.1f} %)"
        text += f", {self.runs} run{'s' * (self.runs != 1)}"
        if self.done >= self.total:
            return text + ", finished"
        if np.isfinite(self.rate):
            text += f", {self.rate:.0f}/s in the latest run, ~{self.seconds_left:.0f} s left"
        return text


def campaign_progress(path) -> CampaignProgress:
    """Where the campaign whose store is `path` stands (`CampaignProgress`), read while it
    runs (from another process) or after it stopped. Raises `ParameterError` for a
    missing file or one that is not a store."""
    path = Path(path)
    if not path.is_file():
        raise ParameterError(f"store {path}: no such file")
    db = _connect(path)
    try:
        meta = _read_meta(db)
        if not meta:
            raise ParameterError(f"store {path} is empty: not a recoil-jax store")
        total = int(meta["total"])
        done = db.execute("SELECT COALESCE(SUM(designs), 0) FROM chunks").fetchone()[0]
        runs, run, started = db.execute(
            "SELECT COUNT(*), MAX(run), MAX(started) FROM runs"
        ).fetchone()
        made, last = db.execute(
            "SELECT COALESCE(SUM(designs), 0), MAX(finished) FROM chunks WHERE run = ?", (run,)
        ).fetchone()
    finally:
        db.close()
    rate = made / (last - started) if made and last and last > started else float("nan")
    left = 0.0 if done >= total else (total - done) / rate if np.isfinite(rate) else float("nan")
    return CampaignProgress(meta["kind"], total, int(done), int(runs), float(rate), float(left))
