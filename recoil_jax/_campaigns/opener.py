"""One way to open a campaign's store: `open_campaign` makes it (stamped with when) or
checks that it is the campaign's own, says on stderr that the campaign resumes, and
closes it whatever happens; `open_study` is the same for a study of a design problem.
A sweep, a search, `optimise` and a calibration all open their stores here."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from .store import StudyStore

__all__ = ["open_campaign", "open_study"]

StoreT = TypeVar("StoreT")


@contextlib.contextmanager
def open_campaign(
    store_class: Callable[..., StoreT],
    path,
    *,
    label: str,
    identity: Callable[[], str],
    total: int,
    plan: dict,
    description: dict,
    progress: bool | None,
    **layout: Any,
) -> Iterator[StoreT | None]:
    """The store of a campaign, as a context manager: None where `path` is None, else
    the `store_class` (`SweepStore`, `StudyStore`, `CalibrationStore`) at `path`, made or
    checked to be this campaign's, and closed on leaving whatever happens (a store may be
    closed before: closing again does nothing).

    **Arguments:**

    - `label`: the campaign as its notices name it (`"sweep"`, `"search"`, ...).
    - `identity`: computes the campaign's identity (`campaign_identity`: it hashes every
      design, so only when there is a store).
    - `total`, `plan`: the work planned (designs, evaluations, fits) and how it is cut,
      for a new store; a store kept from before keeps its own plan.
    - `description`: what the store says it holds (named where another campaign is
      refused it), stamped `created` when the store is made.
    - `progress`: `False`: nothing is printed; else the store's notes
      (`opening_notes`), then one line, `"{label}: resuming from {path}: ..."`, where
      the store holds work done before (`resumed`).
    - `layout`: the store class's own arguments for its tables: `columns` (a sweep's, a
      calibration's), `tune` and `limits` (a study's).

    **Raises:** `ParameterError` where the store cannot be used or is another
    campaign's (`store`)."""
    if path is None:
        yield None
        return
    created = {"created": time.strftime("%Y-%m-%d %H:%M:%S")}
    store: Any = store_class(
        path, identity=identity(), total=total, plan=plan, description=description | created,
        **layout,
    )  # fmt: skip
    try:
        if progress is not False:
            for line in store.opening_notes(label, path, plan):
                print(line, file=sys.stderr)
            if (held := store.resumed()) is not None:
                print(f"{label}: resuming from {path}: {held}", file=sys.stderr)
        yield store
    finally:
        store.close()


def open_study(
    path,
    *,
    label: str,
    problem,
    identity: Callable[[], str],
    total: int,
    plan: dict,
    description: dict,
    progress: bool | None,
) -> contextlib.AbstractContextManager[StudyStore | None]:
    """`open_campaign` of the `StudyStore` at `path` (None: no store) of the study
    `label` (`"search"`, `"optimise"`) of `problem` (a `DesignProblem`: its `tune` and
    `metric_constraints` name the columns; the campaigns import nothing of the design
    layer)."""
    return open_campaign(
        StudyStore, path, label=label, identity=identity, total=total, plan=plan,
        description={"study": label, "tune": list(problem.tune)} | description,
        progress=progress, tune=problem.tune,
        limits=[(name, kind) for name, kind, _ in problem.metric_constraints],
    )  # fmt: skip
