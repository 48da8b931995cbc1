"""One pool of Python threads for the diagnosis' compiled kernels that release the GIL.

A kernel compiled with ``nogil=True`` runs in parallel in plain threads; a ``parallel=True`` kernel would
compile several times slower, and it is the kernels that a fresh install compiles first. The pool has
``numba.get_num_threads()`` workers (1 in the workers of a plant-wide sweep, which are processes already).

Splits nest: work that a split already runs in parallel (a chunk of grid rows, :mod:`~valve_emulator.diagnosis.
fit.scorer`) may call code that splits again (its valves, its columns); such an inner split runs its ranges in
the calling thread, one after the other. The cores are busy with the outer split, and a pool worker that waited
for a range queued behind itself would wait for ever.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numba

__all__ = ["MIN_PER_WORKER", "run_split", "workers_for"]

#: Fewer items than this per worker run in the calling thread: handing work to a thread costs more than it saves.
MIN_PER_WORKER = 16

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()   # diagnoses may run in several threads at once (a Dask worker's)
_inside = threading.local()     # ``split``: this thread runs a range of a split


def workers_for(n: int, per_worker: int = MIN_PER_WORKER) -> int:
    """Threads worth using for ``n`` independent items of which a worker should get at least ``per_worker``
    (1 inside a split: see the module docstring)."""
    if getattr(_inside, "split", False):
        return 1
    return min(max(1, int(numba.get_num_threads())), max(1, n // per_worker))


def _in_split(work: Callable[[int, int], object], a: int, b: int) -> None:
    """``work(a, b)`` with this thread marked as running a range of a split (nested splits run here)."""
    outer = getattr(_inside, "split", False)
    _inside.split = True
    try:
        work(a, b)
    finally:
        _inside.split = outer


def run_split(work: Callable[[int, int], object], cuts: list[int]) -> None:
    """Call ``work(a, b)`` for every consecutive pair of ``cuts`` (non-empty ranges only), one per thread.

    The last range runs in the calling thread; exceptions propagate after every range has finished. Inside a
    range of another split every range runs in the calling thread, in order.
    """
    global _pool, _pool_size
    ranges = [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
    if len(ranges) <= 1 or getattr(_inside, "split", False):
        for a, b in ranges:
            work(a, b)
        return
    with _pool_lock:
        if _pool is None or _pool_size < len(ranges) - 1:
            _pool_size = len(ranges) - 1
            _pool = ThreadPoolExecutor(max_workers=_pool_size, thread_name_prefix="valve_emulator-fit")
        pool = _pool
    futures = [pool.submit(_in_split, work, a, b) for a, b in ranges[:-1]]
    try:
        _in_split(work, *ranges[-1])
    finally:
        for f in futures:
            f.result()
