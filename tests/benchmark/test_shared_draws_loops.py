"""tests/unseen_loops.py: a loop simulated by one worker of a run is read by the others from the run's folder, not
simulated again; outside pytest-xdist (no folder) it is simulated in the process. The other worker is played by a
cleared cache (a process that has not simulated the loop) and a simulator that refuses to be called."""

from __future__ import annotations

import numpy as np
import pytest
import unseen_loops as shared


def _refuse(*args, **kwargs):
    raise AssertionError("simulated again")


def test_a_loop_one_worker_simulated_is_read_by_another_and_is_the_same(tmp_path, monkeypatch):
    monkeypatch.setattr(shared, "_folder", lambda: tmp_path)
    shared.loop.cache_clear()
    rec, truth, nominal = shared.loop("flow_sticky", (7, 2, 0))        # the first worker simulates and shares it
    assert list(tmp_path.glob("*.loop.pickle")) and not list(tmp_path.glob("*.part"))
    shared.loop.cache_clear()                                          # another worker: nothing in memory
    monkeypatch.setattr(shared, "draw", _refuse)
    again, truth_again, nominal_again = shared.loop("flow_sticky", (7, 2, 0))
    for name in ("t", "op", "pv", "sp"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rec, name))
    np.testing.assert_equal(truth_again, truth)
    np.testing.assert_equal(nominal_again, nominal)
    with pytest.raises(AssertionError, match="simulated again"):       # another draw is not in the folder
        shared.loop("flow_sticky", (7, 2, 1))
    shared.loop.cache_clear()


def test_without_a_runs_folder_the_loop_is_simulated_here(monkeypatch):
    monkeypatch.setattr(shared, "_folder", lambda: None)
    shared.loop.cache_clear()
    monkeypatch.setattr(shared, "draw", _refuse)
    with pytest.raises(AssertionError, match="simulated again"):
        shared.loop("flow_sticky", (7, 2, 0))
    shared.loop.cache_clear()
