"""Reading a sweep's store once it is written: its rows, its failures, its best row."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np

from .._campaigns.store import (
    check_model_revision,
    connect_read,
    quote_name,
    read_meta,
    sql_names,
)
from .._model.registry import ParameterError

__all__ = ["lowest_row", "read_sweep_store", "store_failures"]


def _open_sweep(path) -> tuple[sqlite3.Connection, dict[str, str]]:
    """A sweep's store, to read: its connection and `meta` (raises `ParameterError`)."""
    path = Path(path)
    db = connect_read(path)
    meta = read_meta(db)
    if meta.get("kind") != "sweep":
        db.close()
        what = f"a {meta['kind']}'s" if meta else "empty, not a recoil-jax"
        raise ParameterError(f"store {path} is {what} store, not a sweep's")
    try:
        check_model_revision(path, meta)
    except ParameterError:
        db.close()
        raise
    return db, meta


def read_sweep_store(path) -> tuple[dict[str, str], np.ndarray, dict[str, np.ndarray]]:
    """A finished sweep's store: its `meta` (with `seconds`, the chunks' solve time),
    every row's `point` and its columns (`status_code` as integers, NULL as NaN).
    Raises `ParameterError` if the sweep has not finished."""
    db, meta = _open_sweep(path)
    try:
        columns = json.loads(meta["columns"])
        done, seconds = db.execute(
            "SELECT COALESCE(SUM(designs), 0), COALESCE(SUM(seconds), 0) FROM chunks"
        ).fetchone()
        if done < int(meta["total"]):
            raise ParameterError(
                f"store {path} holds {done} of {meta['total']} designs: run the same sweep "
                "with this store to finish it first"
            )
        names = ["point", *sql_names(columns), "status_code"]
        rows = db.execute(f"SELECT {', '.join(map(quote_name, names))} FROM points").fetchall()
    finally:
        db.close()
    table = np.array(rows, dtype=float).reshape(len(rows), len(names))
    total = int(meta["total"])
    if len(rows) != total or len(np.unique(table[:, 0])) != total:
        raise ParameterError(
            f"store {path} holds {len(np.unique(table[:, 0]))} distinct of its {total} designs "
            f"in {len(rows)} rows (rows lost or doubled): run the same sweep with this store "
            "to solve those chunks again"
        )
    data = {name: table[:, j + 1] for j, name in enumerate(columns)}
    data["status_code"] = table[:, -1].astype(np.int32)
    return meta | {"seconds": str(seconds)}, table[:, 0].astype(int), data


def store_failures(path) -> dict[str, int]:
    """A sweep store's failed designs: how many per reason (`status`)."""
    db, _ = _open_sweep(path)
    try:
        rows = db.execute(
            "SELECT status, COUNT(*) FROM points WHERE status != 'ok' GROUP BY status"
        ).fetchall()
    finally:
        db.close()
    return dict(rows)


def lowest_row(path, column: str, ok_code: int) -> dict[str, float] | None:
    """The row of a sweep store with the lowest `column` among the solves that
    succeeded (`status_code == ok_code`), by column name; None if there is none."""
    db, meta = _open_sweep(path)
    columns = json.loads(meta["columns"])
    by_name = dict(zip(columns, sql_names(columns), strict=True))
    sql = quote_name(by_name.get(column, column))
    try:
        cursor = db.execute(
            f"SELECT * FROM points WHERE status_code = ? AND {sql} IS NOT NULL "
            f"ORDER BY {sql} LIMIT 1",
            (ok_code,),
        )
        row = cursor.fetchone()
        names = [d[0] for d in cursor.description]
    finally:
        db.close()
    named = dict(zip(by_name.values(), by_name, strict=True))
    names = [named.get(n, n) for n in names]
    return None if row is None else dict(zip(names, row, strict=True))
