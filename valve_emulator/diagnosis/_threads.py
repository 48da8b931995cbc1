"""One pool of Python threads for the diagnosis' compiled kernels that release the GIL.

A kernel compiled with ``nogil=True`` runs in parallel in plain threads; a ``parallel=True`` kernel would
compile several times slower, and it is the kernels that a fresh install compiles first. The pool has
``numba.get_num_threads()`` workers (1 in the workers of a plant-wide sweep, which are processes already).

While a diagnosis runs, numpy's and scipy's BLAS (OpenBLAS in their wheels) keep to one thread
(:func:`one_blas_thread`, through threadpoolctl): its calls on the record (a residual, a norm, a least-squares
fit) are a few milliseconds each, and after each one OpenBLAS's threads spin on the other cores waiting for
more, where they take the time of the kernels' threads.

Splits nest: work that a split already runs in parallel (a chunk of grid rows, :mod:`~valve_emulator.diagnosis.
fit.scorer`) may call code that splits again (its valves, its columns); such an inner split runs its ranges in
the calling thread, one after the other. The cores are busy with the outer split, and a pool worker that waited
for a range queued behind itself would wait for ever.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait

import numba
from threadpoolctl import ThreadpoolController

__all__ = ["MIN_PER_WORKER", "blas_libraries", "one_blas_thread", "run_each", "run_split", "workers_for"]

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
        wait(futures)   # every range ends before any error is raised: the first future's error must not cut this short
        for f in futures:
            f.result()


def run_each(tasks: list[Callable[[], object]]) -> list:
    """``[task() for task in tasks]``, the tasks shared out over the pool's workers and the calling thread, each
    taking the next task when it is done with one (tasks of unequal length: a polish that converges early).

    For tasks that spend most of their time in kernels that release the GIL. Inside a range of a split, or with
    one thread, they run in the calling thread, in order. Exceptions propagate after every task has finished.
    """
    workers = workers_for(len(tasks), 1)
    if workers <= 1:
        return [task() for task in tasks]
    out: list = [None] * len(tasks)
    taken = iter(range(len(tasks)))
    lock = threading.Lock()

    def take(_a: int, _b: int) -> None:
        while True:
            with lock:
                i = next(taken, None)
            if i is None:
                return
            out[i] = tasks[i]()

    run_split(take, list(range(workers + 1)))
    return out


_blas_lock = threading.Lock()
_blas_users = 0                              # diagnoses running inside :func:`one_blas_thread`
_blas_saved: list[tuple[object, int]] = []   # (controller, the count before) of each BLAS, while any runs


def blas_libraries() -> list:
    """threadpoolctl's controllers of the BLAS libraries loaded in this process now (numpy's and scipy's
    OpenBLAS as their wheels ship them, or MKL, BLIS, ...): each has ``num_threads`` and ``set_num_threads``."""
    return ThreadpoolController().select(user_api="blas").lib_controllers


def one_blas_thread(f: Callable) -> Callable:
    """``f`` run with every BLAS in one thread (see the module docstring), their thread counts restored when the
    last of the calls running at once returns (diagnoses may run in several threads). The numbers are those of
    the same BLAS kernels in one thread. Without a BLAS threadpoolctl knows, ``f`` runs as it is."""

    @functools.wraps(f)
    def single(*args, **kwargs):
        global _blas_users
        with _blas_lock:
            if _blas_users == 0:
                _blas_saved[:] = [(lib, lib.num_threads) for lib in blas_libraries()]
                for lib, _ in _blas_saved:
                    lib.set_num_threads(1)
            _blas_users += 1
        try:
            return f(*args, **kwargs)
        finally:
            with _blas_lock:
                _blas_users -= 1
                if _blas_users == 0:
                    for lib, count in _blas_saved:
                        lib.set_num_threads(count)
    return single
