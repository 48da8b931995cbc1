"""Work items run in worker processes, results in the items' order: the process pool of the plant-wide sweep
and of ``valve-emulator evaluate``.

Each worker is a fresh interpreter (``spawn``: no state inherited from the parent, the same on every platform)
whose compiled kernels run single-threaded (:func:`init_worker`), so ``jobs`` workers use ``jobs`` cores
without oversubscribing them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, TypeVar

__all__ = ["init_worker", "run_ordered"]

_T = TypeVar("_T")
_R = TypeVar("_R")


def init_worker() -> None:
    """Worker-process initialiser: single-threaded compiled kernels, so N workers use N cores without
    oversubscribing them."""
    import numba

    numba.set_num_threads(1)


def run_ordered(work: Callable[[_T], _R], items: Sequence[_T], *, jobs: int = 1,
                done: Callable[[int, _R], Any] | None = None) -> list[_R]:
    """``[work(item) for item in items]``, with ``jobs`` worker processes when ``jobs > 1`` (and more than one
    item). ``done(i, result)`` is called in this process as each item finishes (completion order); the list
    returned is in the items' order. ``work`` and the items must be picklable for ``jobs > 1`` (a module-level
    function). An exception in ``work`` is raised here."""
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    results: list[Any] = [None] * len(items)

    def finished(i: int, result: _R) -> None:
        results[i] = result
        if done is not None:
            done(i, result)

    if jobs == 1 or len(items) <= 1:
        for i, item in enumerate(items):
            finished(i, work(item))
        return results
    with ProcessPoolExecutor(max_workers=min(jobs, len(items)), mp_context=get_context("spawn"),
                             initializer=init_worker) as pool:
        futures = {pool.submit(work, item): i for i, item in enumerate(items)}
        for fut in as_completed(futures):
            finished(futures[fut], fut.result())
    return results
