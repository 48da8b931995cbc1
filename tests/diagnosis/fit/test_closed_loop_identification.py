"""A closed loop's plant is identified so that it cannot be the controller run backwards.

Recordings come from the independent simulator (``valve_emulator.benchmark.independent``), never from the
package's own loop simulation.
"""

import numpy as np
import pytest

from valve_emulator.benchmark.independent import draw
from valve_emulator.diagnosis.fit.closed_loop import Declared, controller_action, identification
from valve_emulator.diagnosis.fit.linear import LinearStructure, fit_one, input_grid_sse
from valve_emulator.errors import UserError


def _negative_plant(seed: int = 1):
    """A first-order plant with gain −2 driven by a random staircase, and its noisy output."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(30, 70, 60), 20)
    x = np.zeros(u.size)
    for k in range(1, u.size):
        x[k] = x[k - 1] + (-2.0 * (u[k - 1] - 50.0) - x[k - 1]) * (1 - np.exp(-1 / 5.0))
    return u, 50.0 + x + rng.normal(0, 0.1, u.size)


def test_a_gain_of_the_forbidden_sign_is_held_at_zero():
    u, y = _negative_plant()
    window = (20, u.size)
    free = fit_one(u, y, window, LinearStructure(taus=(5.0,)), 1.0)
    held = fit_one(u, y, window, LinearStructure(taus=(5.0,), sign=1), 1.0)
    assert free.gain < 0
    assert held.gain == 0.0
    offset_only = float(np.sum((y[window[0]:] - y[window[0]:].mean()) ** 2))
    assert held.sse == pytest.approx(offset_only, rel=1e-6)


def test_the_compiled_grid_scores_the_sign_constraint_as_the_fit_does():
    u, y = _negative_plant(2)
    window = (20, u.size)
    for sign in (1, -1):
        st = LinearStructure(taus=(5.0,), sign=sign)
        sse = input_grid_sse(u, y, window, np.array([0]), st, 1.0)[0, 0]
        assert sse == pytest.approx(fit_one(u, y, window, st, 1.0).sse, rel=1e-4)
    assert input_grid_sse(u, y, window, np.array([0]), LinearStructure(taus=(5.0,), sign=1), 1.0)[0, 0] > \
        10 * input_grid_sse(u, y, window, np.array([0]), LinearStructure(taus=(5.0,), sign=-1), 1.0)[0, 0]


@pytest.mark.parametrize("index", range(4))
def test_the_controllers_action_is_read_from_its_law(index):
    rec, truth, _ = draw("level_sticky", np.random.default_rng([7, index]))
    found = controller_action(rec.op, rec.pv, rec.sp)
    assert found.action == truth["controller"]["action"]
    assert (found.kc > 0) == (truth["plant"]["gain"] > 0)


@pytest.mark.parametrize("index", range(4))
def test_the_controllers_integral_time_is_read_from_its_law(index):
    """Ti in samples, within 2 % of the independent simulator's PI (sampled every second)."""
    rec, truth, _ = draw("level_sticky", np.random.default_rng([7, index]))
    found = controller_action(rec.op, rec.pv, rec.sp)
    assert found.ti * rec.dt == pytest.approx(truth["controller"]["ti"], rel=0.02)


def test_an_integrating_plants_dead_time_is_bounded_by_the_integral_time_only_when_the_law_is_read():
    rec, truth, _ = draw("level_sticky", np.random.default_rng([7, 1]))
    ident = identification(rec.op, rec.pv, rec.sp, dt=rec.dt)
    assert ident.max_delay == pytest.approx(truth["controller"]["ti"], rel=0.02)
    assert ident.delay_bound(True) == ident.max_delay and ident.delay_bound(False) is None
    assert any("integral time" in c for c in ident.constraints)
    noisy = rec.op + np.random.default_rng(0).normal(0.0, 2.0, rec.op.size)   # OP no PI's output any more
    loose = identification(noisy, rec.pv, rec.sp, dt=rec.dt)
    assert loose.max_delay is None and loose.delay_bound(True) is None


def test_declared_loop_type_and_action_decide_the_constraints():
    rec, truth, _ = draw("level_sticky", np.random.default_rng([7, 0]))
    flipped = "direct" if truth["controller"]["action"] == "reverse" else "reverse"
    ident = identification(rec.op, rec.pv, rec.sp, Declared(loop_type="level", action=flipped))
    assert ident.integrating is True
    assert ident.sign == (1 if flipped == "reverse" else -1)
    assert any("declared" in c for c in ident.constraints)
    assert identification(rec.op, rec.pv, rec.sp, Declared(loop_type="flow")).integrating is False


@pytest.mark.parametrize("bad", [dict(loop_type="tank"), dict(action="forward"),
                                 dict(loop_type="level", integrating=False)])
def test_a_wrong_declaration_is_a_user_error(bad):
    with pytest.raises(UserError):
        Declared(**bad)
