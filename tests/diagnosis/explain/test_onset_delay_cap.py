"""Without a model, a dead time far beyond the healthy part's is searched again below it.

The loop is draw 0 of the onset property (:mod:`test_onset_property`): a level loop (dead time 2.7 s behind a
4.6 s lag) whose valve starts to stick at 2340 s of 3000; searched as plant data, its plant came out
self-regulating with a dead time of 30 s, the sticky cycle's shift, and S 2.5 for 4.7.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from unseen_loops import loop

from valve_emulator.diagnosis.explain import pipeline
from valve_emulator.diagnosis.explain.onset import FAR_DELAY, delay_cap, suspect_onset
from valve_emulator.diagnosis.fit.closed_loop import identification
from valve_emulator.diagnosis.fit.data import prepare
from valve_emulator.diagnosis.fit.nominal import identify_before


@pytest.fixture(scope="module")
def level_loop():
    rec, truth, _ = loop("late_onset", (32, 0))
    problem = prepare(rec, validation="twofold")
    constraints = identification(problem.op, problem.pv, rec.sp, dt=problem.dt)
    healthy = identify_before(problem, rec.sp, suspect_onset(problem.pv, rec.sp).sample, constraints=constraints)
    return rec, problem, constraints, healthy


def test_a_dead_time_far_beyond_the_healthy_parts_is_capped_just_above_it(level_loop):
    rec, problem, constraints, healthy = level_loop
    assert 2.7 <= healthy.delay <= 2.7 + 4.6 + 5.0      # the loop's dead time, its lag and 5 s
    cap = delay_cap(problem, rec.sp, 30.0, constraints)
    assert cap == pytest.approx(healthy.delay + problem.dt)


def test_a_dead_time_near_the_healthy_parts_is_left_to_the_search(level_loop):
    rec, problem, constraints, healthy = level_loop
    near = FAR_DELAY * healthy.delay + FAR_DELAY * problem.dt
    assert delay_cap(problem, rec.sp, near, constraints) is None


def test_without_a_set_point_nothing_is_capped(level_loop):
    rec, problem, constraints, _ = level_loop
    assert delay_cap(problem, None, 30.0, constraints) is None


def test_a_change_point_at_a_set_point_move_caps_nothing(level_loop):
    """The step in the control error's energy may be the move's answer, and the part before it no healthy loop:
    the same loop with a small set-point move added at its change point is left to the search."""
    rec, problem, constraints, _ = level_loop
    k = suspect_onset(problem.pv, rec.sp).sample
    sp = np.asarray(rec.sp, dtype=float) + 0.01 * (np.arange(problem.T) >= k)
    assert suspect_onset(problem.pv, sp).sample == k
    assert delay_cap(problem, sp, 30.0, constraints) is None


def _first_search(problem, constraints, delay: float):
    """A stand-in for the first search's outcome as :func:`pipeline._cap` reads it: its dead time, its problem's
    sample time and the identification it ran under."""
    structure = SimpleNamespace(delay=delay)
    return SimpleNamespace(model=SimpleNamespace(fit=SimpleNamespace(structure=structure)), problem=problem,
                           nominal=SimpleNamespace(identification=constraints))


def test_the_identification_says_the_healthy_parts_cap_with_both_dead_times(level_loop, monkeypatch):
    """The answer says which constraint bounded the dead time (issue 32 §2): the healthy part's cap names the
    dead time it allows, the healthy part's own and the one found over the whole record, and the capped
    identification carries that sentence among its constraints."""
    rec, problem, constraints, healthy = level_loop
    monkeypatch.setattr(pipeline, "_setpoint_cap", lambda recording, searched: None)
    cap = pipeline._cap(rec, _first_search(problem, constraints, 30.0), "twofold", (0.0, 100.0))
    assert cap.seconds == pytest.approx(healthy.delay + problem.dt)
    assert f"below {cap.seconds:.3g} s" in cap.said
    assert f"has {healthy.delay:.3g} s" in cap.said and "the 30 s a search found" in cap.said
    assert not cap.leaves_out
    _, nominal = pipeline._prepared(rec, None, {}, lambda line: None, prefilter=None, validation="twofold",
                                    stops=(0.0, 100.0), cap=cap)
    assert cap.said in nominal.identification.constraints
    assert nominal.structure.delay < cap.seconds
