"""The thread pool of the compiled kernels: every range and task runs once, errors reach the caller, callers may
overlap; every BLAS keeps to one thread while a diagnosis runs."""

import functools
import threading
import time

import numba
import pytest
from threadpoolctl import threadpool_limits

from valve_emulator.diagnosis._threads import (
    MIN_PER_WORKER,
    blas_libraries,
    one_blas_thread,
    run_each,
    run_split,
    workers_for,
)


def test_every_non_empty_range_runs_once_and_the_last_in_the_calling_thread():
    seen, lock = [], threading.Lock()

    def work(a, b):
        with lock:
            seen.append((a, b, threading.current_thread() is threading.main_thread()))

    run_split(work, [0, 0, 40, 90, 90, 130])
    assert sorted(r[:2] for r in seen) == [(0, 40), (40, 90), (90, 130)]
    assert [r[2] for r in seen if r[:2] == (90, 130)] == [True]


def test_an_error_in_any_range_reaches_the_caller_after_all_ranges_ran():
    done = []

    def work(a, b):
        if a == 0:
            raise ValueError("range 0")
        done.append(a)

    with pytest.raises(ValueError, match="range 0"):
        run_split(work, [0, 10, 20, 30])
    assert sorted(done) == [10, 20]


def test_an_error_in_the_first_range_waits_for_a_slower_range_of_the_pool():
    """The range that raises ends first and another pool range is still running: the caller gets the error only
    once that range has ended too (on a loaded machine the pool's second range started late, and the error was
    raised while it ran)."""
    done = []

    def work(a, b):
        if a == 0:
            raise ValueError("range 0")
        if a == 10:
            time.sleep(0.3)
        done.append(a)

    with pytest.raises(ValueError, match="range 0"):
        run_split(work, [0, 10, 20, 30])
    assert sorted(done) == [10, 20]


def test_callers_in_several_threads_each_get_all_their_ranges():
    totals = {}

    def caller(k):
        got = []
        run_split(lambda a, b: got.append(b - a), [0, 25, 50, 75, 100])
        totals[k] = sum(got)

    threads = [threading.Thread(target=caller, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert totals == dict.fromkeys(range(8), 100)


def test_small_jobs_stay_in_one_thread():
    assert workers_for(MIN_PER_WORKER - 1) == 1
    assert workers_for(0) == 1


def test_a_split_inside_a_split_runs_its_ranges_in_the_thread_of_the_outer_range():
    """Work that a split runs may split again (a chunk of grid rows, then its valves): the inner ranges all run,
    each in the thread of the outer range that asked, and none waits on a pool busy with the outer split."""
    seen, lock = [], threading.Lock()

    def inner(outer_thread):
        def work(a, b):
            with lock:
                seen.append((a, b, threading.current_thread() is outer_thread))
        return work

    def outer(a, b):
        assert workers_for(10 * MIN_PER_WORKER) == 1
        run_split(inner(threading.current_thread()), [a, (a + b) // 2, b])

    run_split(outer, [0, 40, 80])
    assert sorted(r[:2] for r in seen) == [(0, 20), (20, 40), (40, 60), (60, 80)]
    assert all(r[2] for r in seen)
    assert workers_for(10 * MIN_PER_WORKER) == min(numba.get_num_threads(), 10)   # outside a split again


def _diagnose_counting_pool_ranges(monkeypatch, threads: int):
    """A proof case's diagnosis with its model under ``threads`` numba threads, and how many ranges of a split ran
    outside the calling thread."""
    import valve_emulator as ve
    from valve_emulator.benchmark.cases import CASES, generate
    from valve_emulator.diagnosis import _threads

    pooled = []
    inner = _threads._in_split

    def counting(work, a, b):
        if threading.current_thread() is not threading.main_thread():
            pooled.append((a, b))
        inner(work, a, b)

    monkeypatch.setattr(_threads, "_in_split", counting)
    rec, nominal, _ = generate(CASES[0])
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        d = ve.diagnose(rec, nominal)
    finally:
        numba.set_num_threads(before)
    e = d.explanation
    exact = ([repr(f.parameters) + repr(f.intervals) for f in e.findings],
             [repr(r.delta_bic) + repr(r.heldout) for r in e.ranking], repr(e.plant))
    return d.to_json(), exact, len(pooled)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba launched one thread on this machine")
def test_a_diagnosis_split_over_two_threads_is_the_one_thread_diagnosis_bit_for_bit(monkeypatch):
    """The grid's chunks and the valves' replays split over the cores sum in a fixed order: the document and the
    full-precision numbers behind it do not depend on how many threads ran them (CI's test workers run one each)."""
    one, one_exact, one_pooled = _diagnose_counting_pool_ranges(monkeypatch, 1)
    two, two_exact, two_pooled = _diagnose_counting_pool_ranges(monkeypatch, 2)
    assert one_pooled == 0
    assert two_pooled > 0, "with two threads the diagnosis hands ranges to the pool"
    assert two_exact == one_exact
    assert two == one


def test_each_task_runs_once_and_the_results_come_back_in_order():
    seen, lock = [], threading.Lock()

    def task(i):
        with lock:
            seen.append(i)
        return i * i

    assert run_each([functools.partial(task, i) for i in range(7)]) == [i * i for i in range(7)]
    assert sorted(seen) == list(range(7))
    assert run_each([]) == []


def test_an_error_in_a_task_reaches_the_caller():
    def task(i):
        if i == 2:
            raise ValueError("task 2")
        return i

    with pytest.raises(ValueError, match="task 2"):
        run_each([functools.partial(task, i) for i in range(5)])


def test_every_blas_keeps_to_one_thread_while_a_diagnosis_runs_and_gets_its_count_back_after():
    # numpy's and scipy's wheels each bring an OpenBLAS; whatever the environment set (CI sets one thread),
    # the test starts them at two so that "one inside" and "back after" are both seen.
    assert blas_libraries(), "numpy and scipy bring a BLAS that threadpoolctl controls"
    counts = lambda: [lib.num_threads for lib in blas_libraries()]   # noqa: E731
    inside = []

    @one_blas_thread
    def diagnosis(depth):
        inside.append(counts())
        if depth:
            diagnosis(depth - 1)   # one running inside another (or beside it) does not restore the count early
            inside.append(counts())

    with threadpool_limits(limits=2, user_api="blas"):
        before = counts()
        assert before == [2] * len(before)
        diagnosis(1)
        assert counts() == before
    assert all(c == [1] * len(before) for c in inside)
