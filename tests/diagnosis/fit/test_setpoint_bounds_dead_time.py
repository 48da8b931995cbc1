"""The set point's path bounds the plant's dead time (:func:`~valve_emulator.diagnosis.fit.closed_loop.
setpoint_delay`), known truth from the independent simulator.

OP answers a set-point step at once, so PV cannot answer it sooner than the plant's dead time; the closed test
of PV's step response from the set point, run downward from a dead time a search found, gives the fewest
samples within which PV answers. Three loops of the shared draws (``tests/unseen_loops.py``):

- the sticky level loop 32.14 (dead time 0.3 s behind a 7.6 s lag), whose search without a model found a
  self-regulating plant with a 69 s dead time, the sticky cycle's shift;
- the aggressive PI loop 1.2.17 (dead time 8.1 s, no lag): the bound sits just above the truth and never below;
- the aggressive PI loop 1.2.0 (dead time 8.6 s behind a 4.8 s lag), whose search found 13.6 s, the lag taken
  up into the dead time: refuted, but not far beyond the bound, so no search is capped there.
"""

from __future__ import annotations

import numpy as np
import pytest
from unseen_loops import loop

from valve_emulator.diagnosis.explain.onset import far_beyond
from valve_emulator.diagnosis.fit.closed_loop import setpoint_delay


@pytest.fixture(scope="module")
def level_loop():
    return loop("level_sticky", (32, 14))


@pytest.fixture(scope="module")
def dead_time_loop():
    return loop("aggressive_pi", (1, 2, 17))


def test_a_sticky_level_loops_cycle_shift_is_far_beyond_the_set_points_bound(level_loop):
    rec, truth, _ = level_loop
    m = setpoint_delay(rec.pv, rec.sp, 69)
    assert m is not None
    assert m * rec.dt > truth["plant"]["delay"]          # never below the truth
    assert far_beyond(69.2, m * rec.dt, rec.dt)           # the 69 s dead time is searched again below it


@pytest.mark.parametrize("longest", [12, 20, 40])
def test_the_bound_lies_at_or_above_the_true_dead_time(dead_time_loop, longest):
    rec, truth, _ = dead_time_loop
    m = setpoint_delay(rec.pv, rec.sp, longest)
    assert m is not None
    # OP answers the set point at once, held over each sample: a dead time θ shows in PV from the first sample
    # after θ on, so the bound is above θ, by at most a few samples.
    assert truth["plant"]["delay"] < m * rec.dt <= truth["plant"]["delay"] + 3 * rec.dt


@pytest.mark.parametrize("longest", [3, 6, 8])
def test_a_dead_time_shorter_than_the_truth_is_not_refuted(dead_time_loop, longest):
    rec, truth, _ = dead_time_loop
    assert longest * rec.dt < truth["plant"]["delay"]
    assert setpoint_delay(rec.pv, rec.sp, longest) is None


def test_a_lag_taken_up_into_the_dead_time_is_not_far_beyond_the_bound():
    rec, truth, _ = loop("aggressive_pi", (1, 2, 0))
    m = setpoint_delay(rec.pv, rec.sp, 13)
    assert m is not None and m * rec.dt > truth["plant"]["delay"]
    assert not far_beyond(13.6, m * rec.dt, rec.dt)


def test_without_a_moving_set_point_there_is_no_bound(level_loop):
    rec, _, _ = level_loop
    assert setpoint_delay(rec.pv, None, 69) is None
    assert setpoint_delay(rec.pv, np.full(len(rec.pv), 50.0), 69) is None
    assert setpoint_delay(rec.pv, np.where(np.arange(len(rec.pv)) > 10, np.nan, 50.0), 69) is None
