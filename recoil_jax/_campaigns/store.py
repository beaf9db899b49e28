"""Campaign stores: a sweep's results committed to an SQLite file chunk by chunk, and a
study's evaluations one by one, so that a run that is killed resumes where it stopped.

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

A study's store (`StudyStore`) has `meta` and `runs` too, and instead of `points` and
`chunks`:

- `evaluations`: one row per evaluation, in the order they were made: `evaluation`,
  `run`, `seconds` (of the study's time budget, runs before included), `phase`
  (`"sample"`: the global phase, `"local"`: a gradient solve of a local run, `"step"`:
  a step of an optax run), `start` (the optax run; NULL otherwise), the tuned
  parameters by flat name, `objective` (exact), the normalised violation of each limit
  (`violation:<metric>:<max|min>`, `<= 0` where held), `violation` (the largest),
  `feasible`, `status`, `status_code`; and for the resume, `key` (a digest of what was
  evaluated) and `outputs` (the evaluation's arrays, bit for bit, as `.npz` bytes).
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import socket
import sqlite3
import sys
import threading
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._model.feasibility import (
    feasible,
    largest_violation,
)
from .._model.forces.family import outside_source
from .._model.registry import ParameterError
from .._model.status import OK_CODE, status_messages
from .._version import __version__

__all__ = [
    "MODEL_REVISION",
    "CalibrationStore",
    "StudyStore",
    "SweepStore",
    "campaign_identity",
    "check_model_revision",
    "connect_read",
    "evaluation_row",
    "fingerprint",
    "quote_name",
    "read_meta",
    "sql_names",
]

#: The layout of the tables; a store of another format is refused, not misread.
STORE_FORMAT = 1
#: What each revision of the model's semantics changed (`docs/model.md`): a store's
#: results were made by one (`meta`'s `model`; a store from before revision 2 has none),
#: and a store made by another is refused, never resumed or read on its semantics
#: (`check_model_revision`).
MODEL_REVISIONS = {
    2: "the firing envelope's revision 2: the gun fires from its static rest, "
    "displacements are measured from it, the stability margin is the whole gun's, and "
    "the pull and the mount load are metrics",
    3: "the barrel's stick on its rails is a mode of the solve, switched exactly at "
    "events, and the friction's smoothing widths are gone",
}
#: The revision this version's results are made by.
MODEL_REVISION = max(MODEL_REVISIONS)


def campaign_identity(kind: str, *parts: Any) -> str:
    """A campaign's identity in its store: the `fingerprint` of its kind, the package's
    version and `parts` (what makes its results: the problem, the settings)."""
    return fingerprint(kind, __version__, *parts)


def fingerprint(*parts: Any) -> str:
    """A SHA-256 digest of pytrees (their structure, static fields included, every
    leaf's dtype, shape and bytes, and the code of any part defined outside the
    package): equal for equal inputs, bit for bit."""
    digest = hashlib.sha256()
    for part in parts:
        leaves, treedef = jax.tree.flatten(part)
        digest.update(_as_before_added_parts(str(treedef)).encode())
        digest.update(outside_source(part).encode())  # ("" for the built-in parts)
        for leaf in leaves:
            array = np.ascontiguousarray(np.asarray(leaf))
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


#: Where a design's node begins in a structure's text (`str(treedef)`).
_DESIGN_NODE = "CustomNode(RecoilParams["


def _as_before_added_parts(text: str) -> str:
    """A structure's text with each design's empty `added` (no part added outside the
    package: its last child, `()`) left out, as the text was before designs could hold
    added parts; so that a store's identity, and a store written then, stay valid."""
    pieces, start = [], 0
    while (node := text.find(_DESIGN_NODE, start)) >= 0:
        children = text.index("], [", node) + 3  # the `[` that opens its children
        depth, end = 0, children
        for end in range(children, len(text)):
            depth += (text[end] in "([{") - (text[end] in ")]}")
            if depth == 0:
                break
        empty = end - 4 >= children and text[end - 4 : end] == ", ()"
        pieces.append(text[start : end - 4] if empty else text[start:end])
        start = end
    return "".join(pieces) + text[start:]


def quote_name(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def sql_names(columns: list[str]) -> list[str]:
    """The SQL names of a table's value columns. SQLite's names ignore case, and the
    barrel's `M` and the absorber's `m` are both parameters: the first keeps its name, a
    later one equal to it but for case is stored as `name~2` (`~3`, ...)."""
    seen: dict[str, int] = {}
    out = []
    for name in columns:
        count = seen[name.lower()] = seen.get(name.lower(), 0) + 1
        out.append(name if count == 1 else f"{name}~{count}")
    return out


def _connect(path: Path) -> sqlite3.Connection:
    """An SQLite connection in autocommit mode (transactions are explicit), write-ahead
    logged: a killed writer leaves the last committed transaction intact. (`_Store`
    checked the path and made its folder.)"""
    writable = path if path.exists() else path.parent
    if not os.access(writable, os.W_OK):
        what = "cannot be written" if path.exists() else f"cannot be made in {path.parent}"
        raise ParameterError(f"store {path} {what} (permission denied): give another path")
    try:
        # Shared by a study's threads, each write under the store's lock.
        db = sqlite3.connect(path, isolation_level=None, timeout=60.0, check_same_thread=False)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master")}
    except sqlite3.OperationalError as error:  # read-only, full, or a file system fault
        raise ParameterError(f"store {path} cannot be used ({error}): give another path") from None
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


def _hold(path: Path):
    """The store's writer lock: an exclusive `flock` on `FILE.lock` beside it, held
    until the store closes (the kernel lets go of it when the process ends, killed or
    not). The lock file says who holds it. A second writer is refused, naming the
    holder: two writers would solve and store the same designs twice. None where the
    platform has no `flock` (Windows)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover
        return None
    path = path.resolve()  # one lock for every name of the file (links, relative paths)
    lock_path = path.with_name(path.name + ".lock")
    try:
        handle = open(lock_path, "a+")  # held until the store closes
    except OSError as error:
        raise ParameterError(
            f"store {path}: cannot make its lock file {lock_path} ({error.strerror})"
        ) from None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as error:
        if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise ParameterError(
                f"store {path} is in use by {holder}: wait for that run to end (or stop "
                "it), or give another store; two runs on one store would solve everything "
                "twice"
            ) from None
        handle.close()  # a file system without flock (some network ones): no lock
        print(f"recoil-jax: warning: store {path}: its file system cannot lock it "
              f"({error.strerror}); run one command on it at a time", file=sys.stderr)  # fmt: skip
        return None
    handle.seek(0)
    handle.truncate()
    handle.write(
        f"process {os.getpid()} on {socket.gethostname()} since "
        f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n"
    )
    handle.flush()
    return handle


def connect_read(path: Path) -> sqlite3.Connection:
    """A read-only connection to an existing store (`progress` and the readers never
    write into it, not even a new database into an empty file)."""
    if not path.is_file():
        what = "no such file" if not path.exists() else "not a regular file"
        raise ParameterError(f"store {path}: {what}")
    if path.stat().st_size == 0:
        raise ParameterError(f"store {path} is empty: not a recoil-jax store")
    try:
        db = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True, timeout=60.0)
        db.execute("SELECT name FROM sqlite_master").fetchall()
    except sqlite3.OperationalError as error:  # a folder it cannot read, a lock, ...
        raise ParameterError(f"store {path} cannot be opened ({error})") from None
    except sqlite3.DatabaseError as error:
        raise ParameterError(f"store {path} is not a recoil-jax store ({error})") from None
    return db


def read_meta(db: sqlite3.Connection) -> dict[str, str]:
    tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master")}
    if "meta" not in tables:
        return {}
    return dict(db.execute("SELECT key, value FROM meta").fetchall())


class _Store:
    """What every store does on opening: create it, or check that it was made by the same
    campaign (`identity`, a `fingerprint` of everything its results depend on) and raise
    `ParameterError` if not; keep the `plan` of the run that made it; add a row to
    `runs`. A subclass names its `kind` and writes its tables in `_create_tables`."""

    kind = ""

    def __init__(self, path, *, identity: str, total: int, plan: dict, columns, description):
        self.path = Path(path)
        if self.path.is_dir():
            raise ParameterError(f"store {self.path} is a folder: give the path of a file")
        if self.path.exists() and not self.path.is_file():  # /dev/null, a pipe, a socket
            raise ParameterError(f"store {self.path} is not a regular file: give a file's path")
        if self.path.is_file() and self.path.stat().st_size:
            with open(self.path, "rb") as file:  # before a lock file is made beside it
                header = file.read(16)
            if header != b"SQLite format 3\x00":
                raise ParameterError(
                    f"store {self.path} is not a recoil-jax store (not an SQLite file): give "
                    "a new path"
                )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _hold(self.path)
        try:
            self.db = _connect(self.path)
        except BaseException:
            self._release()
            raise
        try:
            meta = read_meta(self.db)
            if meta:
                self._check(meta, identity)
                self.plan = json.loads(meta["plan"])
                self.columns = json.loads(meta["columns"])
            else:
                self.plan, self.columns = plan, list(columns)
                self._create(identity, total, description)
        except BaseException:
            self.db.close()
            self._release()
            raise
        self.total = total
        cursor = self.db.execute(
            "INSERT INTO runs (started, pid, host) VALUES (?, ?, ?)",
            (time.time(), os.getpid(), socket.gethostname()),
        )
        self.run = cursor.lastrowid

    def _check(self, meta: dict[str, str], identity: str) -> None:
        check_model_revision(self.path, meta)
        kind, made = meta.get("kind"), json.loads(meta.get("description", "{}"))
        if kind != self.kind or meta.get("identity") != identity:
            what = f"a different {self.kind}" if kind == self.kind else f"a {kind}"
            raise ParameterError(
                f"store {self.path} holds the results of {what} ({_describe(kind, made)}), "
                "not of this one: give a new store path, or delete the file to start again"
            )
        if int(meta.get("format", -1)) != STORE_FORMAT:
            raise ParameterError(
                f"store {self.path} was written in store format {meta.get('format')}; this "
                f"version reads format {STORE_FORMAT}: give a new store path"
            )

    def _transaction(self, write) -> Any:
        """`write(db)` in one transaction: all of its rows or none."""
        db = self.db
        db.execute("BEGIN IMMEDIATE")
        try:
            out = write(db)
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:  # SQLite may have rolled back itself (a full disk)
                db.execute("ROLLBACK")
            raise
        return out

    def _create(self, identity: str, total: int, description: dict) -> None:
        def write(db):
            db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
            db.execute(
                "CREATE TABLE runs (run INTEGER PRIMARY KEY AUTOINCREMENT, started REAL, "
                "pid INTEGER, host TEXT)"
            )
            self._create_tables()
            meta = {
                "kind": self.kind,
                "format": str(STORE_FORMAT),
                "model": str(MODEL_REVISION),
                "identity": identity,
                "total": str(total),
                "plan": json.dumps(self.plan),
                "columns": json.dumps(self.columns),
                "description": json.dumps(description),
            }
            db.executemany("INSERT INTO meta VALUES (?, ?)", list(meta.items()))

        self._transaction(write)

    def _create_tables(self) -> None:
        raise NotImplementedError

    def opening_notes(self, label: str, path, plan: dict) -> list[str]:
        """Lines a campaign `label` says on stderr as it opens this store at `path` (as
        given), before its resume notice (`open_campaign`); `plan`: the plan it asked
        for. None by default."""
        return []

    def resumed(self) -> str | None:
        """What the resume notice says this store holds (`"{label}: resuming from
        {path}: {resumed}"`); None when it holds nothing yet."""
        raise NotImplementedError

    def close(self) -> None:
        """Close the database and let go of the writer lock; closing again does nothing."""
        self.db.close()
        self._release()

    def _release(self) -> None:
        """Let go of the writer lock (the lock file stays, saying who held it last)."""
        if self._writer is not None:
            self._writer.close()  # closing the file releases its flock
            self._writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SweepStore(_Store):
    """A sweep's store (see the module's docstring). `plan` (the chunking: workers, lanes,
    chunk size) is kept from the run that made the store, so that a resumed sweep cuts
    the same chunks and gives the same bits. Opening it forgets the chunks whose rows
    are not all there (`drop_incomplete`; `dropped`: how many designs they held), which
    the sweep solves again."""

    kind = "sweep"

    def __init__(self, path, *, identity: str, total: int, plan: dict, columns, description):
        super().__init__(
            path, identity=identity, total=total, plan=plan, columns=columns,
            description=description,
        )  # fmt: skip
        try:
            self.dropped = self.drop_incomplete()
        except BaseException:
            self.close()
            raise

    def opening_notes(self, label: str, path, plan: dict) -> list[str]:
        """The plan kept from the run that made the store, where it is not `plan`; the
        chunks dropped as incomplete (`dropped`), which are solved again."""
        notes = []
        if self.plan != plan:
            notes.append(
                f"{label}: resuming with the plan of the run that made {path} ({self.plan}), "
                f"not {plan}: the same chunks give the same results"
            )
        if self.dropped:
            notes.append(
                f"{label}: {path} had chunks with rows missing or doubled ({self.dropped} "
                "designs dropped): those chunks are solved again"
            )
        return notes

    def resumed(self) -> str | None:
        done = self.done()
        already = sum(done.values())
        if not already:
            return None
        return (
            f"{already} of {self.total} designs ({len(done)} chunk{'s' * (len(done) != 1)}) "
            "already done"
        )

    def _create_tables(self) -> None:
        data = ", ".join(f"{quote_name(name)} REAL" for name in sql_names(self.columns))
        self.db.execute(
            "CREATE TABLE chunks (chunk TEXT PRIMARY KEY, designs INTEGER, seconds REAL, "
            "finished REAL, run INTEGER)"
        )
        # Rows in the order they were committed, `point` not a key: a chunk's points
        # are scattered over the sweep (sorted by gap), and keeping them in a B-tree
        # by point made each commit 4 times slower. Each chunk is written once, in
        # one transaction with its row in `chunks`.
        self.db.execute(
            f"CREATE TABLE points (point INTEGER, chunk TEXT, {data}, "
            "status TEXT, status_code INTEGER)"
        )

    def done(self) -> dict[str, int]:
        """The committed chunks: key -> number of designs."""
        return dict(self.db.execute("SELECT chunk, designs FROM chunks").fetchall())

    def drop_incomplete(self) -> int:
        """Forget every committed chunk whose rows are not all there (lost, deleted by
        hand) or are there twice, so that it is solved again rather than read as zeros;
        returns how many designs those chunks hold."""
        rows = dict(self.db.execute("SELECT chunk, COUNT(*) FROM points GROUP BY chunk").fetchall())
        done = self.done()
        broken = [c for c, n in done.items() if rows.get(c, 0) != n]
        stray = [c for c in rows if c not in done]

        def write(db) -> int:
            for chunk in broken + stray:
                db.execute("DELETE FROM points WHERE chunk = ?", (chunk,))
                db.execute("DELETE FROM chunks WHERE chunk = ?", (chunk,))
            return sum(int(done.get(c) or rows.get(c) or 0) for c in broken + stray)

        return self._transaction(write) if broken or stray else 0

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
        names = ["point", "chunk", *sql_names(self.columns), "status", "status_code"]
        insert = (
            f"INSERT INTO points ({', '.join(map(quote_name, names))}) "
            f"VALUES ({', '.join('?' * len(names))})"
        )

        def write(db) -> bool:
            if db.execute("SELECT 1 FROM chunks WHERE chunk = ?", (chunk,)).fetchone():
                return False
            db.executemany(insert, rows)
            db.execute(
                "INSERT INTO chunks VALUES (?, ?, ?, ?, ?)",
                (chunk, len(points), seconds, time.time(), self.run),
            )
            return True

        return self._transaction(write)

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
        names = ["point", *sql_names(self.columns), "status_code"]
        rows = self.db.execute(
            f"SELECT {', '.join(map(quote_name, names))} FROM points "
            "WHERE chunk IN (SELECT chunk FROM wanted)"
        ).fetchall()
        table = np.array(rows, dtype=float).reshape(len(rows), len(names))
        data = {name: table[:, j + 1] for j, name in enumerate(self.columns)}
        data["status_code"] = table[:, -1].astype(np.int32)
        return table[:, 0].astype(int), data


class CalibrationStore(_Store):
    """A calibration's store: each part of the fit committed with its outputs as it
    finishes (a chunk of starts `fit:<first>`, the profiles `profiles`), so that a killed
    calibration resumes with the parts it had. `chunks` as a sweep's (`designs`: the
    fits in the part), with the part's arrays in `outputs` (`.npz` bytes, bit for bit);
    `plan`: `starts_per_chunk`, kept from the run that made the store."""

    kind = "calibration"

    def _create_tables(self) -> None:
        self.db.execute(
            "CREATE TABLE chunks (chunk TEXT PRIMARY KEY, designs INTEGER, seconds REAL, "
            "finished REAL, run INTEGER, outputs BLOB)"
        )

    def stored_fits(self) -> int:
        """How many fits the committed parts hold."""
        return int(self.db.execute("SELECT COALESCE(SUM(designs), 0) FROM chunks").fetchone()[0])

    def resumed(self) -> str | None:
        fits = self.stored_fits()
        return f"{fits} fits already done" if fits else None

    def stored(self, part: str) -> dict[str, np.ndarray] | None:
        """The arrays of the committed `part`, or None."""
        row = self.db.execute("SELECT outputs FROM chunks WHERE chunk = ?", (part,)).fetchone()
        return None if row is None else unpack(row[0])

    def commit(self, part: str, fits: int, arrays: dict[str, Any], seconds: float) -> None:
        """Write one part (`fits`: how many fits it holds) in one transaction."""
        blob = pack(arrays)
        self._transaction(
            lambda db: db.execute(
                "INSERT OR IGNORE INTO chunks VALUES (?, ?, ?, ?, ?, ?)",
                (part, fits, seconds, time.time(), self.run, blob),
            )
        )


def check_model_revision(path, meta: dict[str, str]) -> None:
    """Refuse (`ParameterError`, one line saying why and what to do) a store whose results
    were made by another revision of the model's semantics (`MODEL_REVISION`; a store
    from before revision 2 has none), naming what changed since."""
    if not meta or meta.get("model") == str(MODEL_REVISION):
        return
    made = meta.get("model", "1")
    if made.isdigit() and int(made) > MODEL_REVISION:
        raise ParameterError(
            f"store {path} was made by revision {made} of the model, by a newer recoil-jax "
            f"than this one (revision {MODEL_REVISION}): upgrade recoil-jax to resume or "
            "read it, or run the campaign again with a new store path"
        )
    later = [v for k, v in MODEL_REVISIONS.items() if not made.isdigit() or k > int(made)]
    changed = "; ".join(later)
    raise ParameterError(
        f"store {path} was made by revision {made} of the model, and this is revision "
        f"{MODEL_REVISION} ({changed}): its results are not this model's. Run the "
        "campaign again with a new store path (or delete the file)"
    )


def pack(arrays: dict[str, Any]) -> bytes:
    """Named arrays as compressed `.npz` bytes (read back bit for bit by `unpack`)."""
    buffer = io.BytesIO()
    named: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
    np.savez_compressed(buffer, **named)
    return buffer.getvalue()


# `np.load` parses each array's header with `ast.literal_eval`; CPython 3.11 keeps the
# AST builder's depth counter per interpreter, not per thread, so two threads parsing at
# once can fail with "SystemError: AST constructor recursion depth mismatch"
# (python/cpython#106905). A study's local runs replay stored outputs from their threads.
_UNPACK_LOCK = threading.Lock()


def unpack(blob: bytes) -> dict[str, np.ndarray]:
    """The named arrays of `pack`'s bytes. Thread-safe: one header parsed at a time."""
    with _UNPACK_LOCK, np.load(io.BytesIO(blob), allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


class StudyStore(_Store):
    """A study's store (see the module's docstring): every evaluation committed as it is
    made, with its outputs, so that a resumed study replays what is stored (`stored`) and
    solves only the rest. Thread-safe: a study's local runs commit from their threads.

    - `tune`: the tuned parameters' flat names; `limits`: `(metric, kind)` per limit;
    - `plan`: kept from the run that made the store (`workers`: how many local runs at
      once, which sets how basin hopping proceeds);
    - `prior_seconds`: the time budget the earlier runs spent."""

    kind = "study"

    def __init__(self, path, *, identity: str, total: int, plan: dict, tune, limits, description):
        self.tune = list(tune)
        self.limit_columns = [f"violation:{name}:{kind}" for name, kind in limits]
        columns = [*self.tune, "objective", *self.limit_columns]
        super().__init__(
            path, identity=identity, total=total, plan=plan, columns=columns,
            description=description,
        )  # fmt: skip
        self.lock = threading.Lock()
        rows = self.db.execute("SELECT key, outputs FROM evaluations WHERE key IS NOT NULL")
        self._outputs: dict[str, bytes] = dict(rows.fetchall())
        self.evaluation_count, prior = self.db.execute(
            "SELECT COUNT(*), COALESCE(MAX(seconds), 0) FROM evaluations"
        ).fetchone()
        self.prior_seconds = float(prior)
        self.replayed = 0
        self._opened = time.perf_counter()

    def spent(self) -> float:
        """Seconds of the study's time budget spent: the earlier runs' and this one's."""
        return self.prior_seconds + time.perf_counter() - self._opened

    def resumed(self) -> str | None:
        if not self.evaluation_count:
            return None
        return (
            f"{self.evaluation_count} evaluations stored (read back, not solved), "
            f"{self.prior_seconds:.1f} s of the budget spent"
        )

    def _create_tables(self) -> None:
        data = ", ".join(f"{quote_name(name)} REAL" for name in sql_names(self.columns))
        self.db.execute(
            "CREATE TABLE evaluations (evaluation INTEGER PRIMARY KEY AUTOINCREMENT, "
            f"run INTEGER, seconds REAL, phase TEXT, start INTEGER, {data}, violation REAL, "
            "feasible INTEGER, status TEXT, status_code INTEGER, key TEXT, outputs BLOB)"
        )
        self.db.execute(
            "CREATE TABLE checkpoints (step INTEGER PRIMARY KEY, run INTEGER, state BLOB)"
        )

    def stored(self, key: str) -> dict[str, np.ndarray] | None:
        """The outputs of the evaluation named `key`, if it is in the store."""
        with self.lock:
            blob = self._outputs.get(key)
            if blob is not None:
                self.replayed += 1
        return None if blob is None else unpack(blob)

    def commit(self, rows: list[dict[str, Any]]) -> None:
        """Write evaluations in one transaction. Each row: `seconds`, `phase`, `theta
        (P,)`, `objective`, `violations (C,)`, `feasible`, `status`, `status_code`, and
        optionally `start`, `key` and `outputs` (named arrays, kept for the resume)."""
        insert, values, blobs = self._insert(rows)
        with self.lock:
            self._transaction(lambda db: db.executemany(insert, values))
            self._outputs.update(blobs)

    def checkpoint(self, step: int, state: dict[str, Any], rows: list[dict[str, Any]]) -> None:
        """Commit one step of an optax run: its evaluations (`rows`, as `commit`) and the
        state to resume from (named arrays), in one transaction."""
        insert, values, _ = self._insert(rows)
        blob = pack(state)

        def write(db):
            db.executemany(insert, values)
            db.execute(
                "INSERT OR REPLACE INTO checkpoints VALUES (?, ?, ?)", (step, self.run, blob)
            )

        with self.lock:
            self._transaction(write)

    def _insert(self, rows: list[dict[str, Any]]):
        names = [
            "run", "seconds", "phase", "start", *sql_names(self.columns), "violation", "feasible",
            "status", "status_code", "key", "outputs",
        ]  # fmt: skip
        values, blobs = [], {}
        for row in rows:
            violations = np.asarray(row["violations"], dtype=float).reshape(-1)
            blob = pack(row["outputs"]) if row.get("outputs") is not None else None
            if row.get("key") is not None and blob is not None:
                blobs[row["key"]] = blob
            values.append(
                (
                    self.run,
                    float(row["seconds"]),
                    row["phase"],
                    row.get("start"),
                    *np.asarray(row["theta"], dtype=float).reshape(-1).tolist(),
                    float(row["objective"]),
                    *violations.tolist(),
                    float(largest_violation(violations)) if violations.size else None,
                    int(bool(row["feasible"])),
                    row["status"],
                    int(row["status_code"]),
                    row.get("key"),
                    blob,
                )
            )
        insert = (
            f"INSERT INTO evaluations ({', '.join(map(quote_name, names))}) "
            f"VALUES ({', '.join('?' * len(names))})"
        )
        return insert, values, blobs

    def checkpoints(self) -> list[dict[str, np.ndarray]]:
        """Every committed step's state, in step order."""
        rows = self.db.execute("SELECT state FROM checkpoints ORDER BY step").fetchall()
        return [unpack(blob) for (blob,) in rows]


def evaluation_row(
    seconds: float,
    phase: str,
    theta,
    objective,
    violations,
    status_code,
    *,
    start: int | None = None,
    key: str | None = None,
    outputs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One evaluation as a row of a study's store (`StudyStore.commit`): its feasibility
    (`feasible`) and status message follow from the status code."""
    code = int(status_code)
    return {
        "seconds": seconds, "phase": phase, "start": start, "theta": theta,
        "objective": objective, "violations": violations,
        "feasible": bool(feasible(code == OK_CODE, objective, violations)),
        "status": status_messages(np.asarray([code]))[0], "status_code": code,
        "key": key, "outputs": outputs,
    }  # fmt: skip


def _describe(kind: str | None, description: dict) -> str:
    if kind == "study":
        parts = [f"study {description.get('study', '?')}"]
        if description.get("tune"):
            parts.append("tuning " + ", ".join(description["tune"]))
    elif kind == "calibration":
        parts = [f"a calibration of {', '.join(description.get('fit', ['?']))}"]
        parts.append(f"{description.get('starts', '?')} starts")
    else:
        parts = [f"{description.get('designs', '?')} designs"]
        if description.get("names"):
            parts.append("of " + ", ".join(description["names"]))
    if description.get("created"):
        parts.append(f"made {description['created']}")
    return ", ".join(parts)
