"""The OPC UA process builds its address space out of the garbage collector's sight and serves with the collector's
young generation at :data:`~valve_emulator.opcua.remote.SERVING_GC_THRESHOLDS` (docs/benchmarks.md §9.21: with
Python's 700 the collector took 15 % of the process's CPU at 10 clients). Checked on the context manager the child
runs its build in; this process's collector runs as before afterwards
(what the build froze stays frozen, as the test session's own start-up objects are, tests/conftest.py)."""

import gc

from valve_emulator.opcua.remote import SERVING_GC_THRESHOLDS, _built_out_of_the_collectors_sight


def test_the_build_runs_without_the_collector_and_serving_runs_it_at_the_serving_thresholds():
    before, enabled, frozen = gc.get_threshold(), gc.isenabled(), gc.get_freeze_count()
    try:
        with _built_out_of_the_collectors_sight():
            assert not gc.isenabled()
            built = [[] for _ in range(10)]   # lists: objects the collector tracks
        assert gc.isenabled()
        assert gc.get_threshold() == SERVING_GC_THRESHOLDS
        assert SERVING_GC_THRESHOLDS[0] > 700   # fewer young collections than Python's default while serving
        assert gc.get_freeze_count() >= frozen + len(built)   # what was built is out of the collector's sight
    finally:
        gc.set_threshold(*before)
        (gc.enable if enabled else gc.disable)()
