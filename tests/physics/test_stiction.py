"""The three stiction state machines: published behaviour, shared properties, robustness, bad input."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from valve_emulator.stiction import (
    MODELS,
    StictionBank,
    Valve,
    rest_samples_for,
    seed_to_2005,
    simulate,
    simulate_many,
)


def triangle(level, amplitude, step, cycles):
    """OP rising from ``level`` to level+A, then down to level-A and up again, ``cycles`` times.

    Steps are ``step`` on the first rise and ``2*step`` afterwards; the slope is never exactly zero.
    """
    n_quarter = int(np.ceil(amplitude / step))
    up = np.linspace(0, amplitude, n_quarter + 1)[1:]
    body = np.concatenate([up] + [np.concatenate([amplitude - 2 * up, -amplitude + 2 * up])] * cycles)
    return np.concatenate([[0.0], body]) + level


params = st.tuples(
    st.floats(0.5, 10.0),  # S
    st.floats(0.0, 12.0),  # J (covers overshoot J > S)
    st.floats(0.005, 0.05),  # step
)


@settings(max_examples=60, deadline=None)
@given(params, st.floats(1.05, 3.0), st.sampled_from(MODELS))
def test_properties_hold_for_every_model(p, amp_factor, model):
    S, J, step = p
    A = amp_factor * max(S, J)  # large enough for the valve to move in both directions
    assume(50 + A + S < 100 and 50 - A - S > 0)
    op = triangle(50.0, A, step, cycles=3)
    mv = simulate(op, S=S, J=J, model=model)

    assert np.all((mv >= 0) & (mv <= 100))
    dmv = np.diff(mv)
    dop = np.diff(op)
    max_step = np.abs(dop).max()
    moved = np.flatnonzero(dmv != 0) + 1
    assert moved.size > 0

    # While moving (every sample where MV changes) MV = OP - sign*(S - J)/2, sign = direction of motion.
    d = np.sign(dmv[moved - 1])
    np.testing.assert_allclose(mv[moved], op[moved] - d * (S - J) / 2, atol=1e-9)

    # After each reversal of OP, MV holds until OP has travelled S, and the breakaway jump is J.
    reversals = np.flatnonzero(np.sign(dop[1:]) != np.sign(dop[:-1])) + 1
    for r in reversals[1:]:  # skip the start-up: the first reversal may find the valve stuck from rest
        direction = np.sign(dop[r])
        later = np.flatnonzero(moved > r)
        assert later.size, "the valve never broke away after a reversal"
        k = moved[later[0]]
        travel = direction * (op[k] - op[r])
        assert travel > S - 1e-9, f"moved after only {travel} % of OP travel (S = {S})"
        if model != "he" or max_step >= J:
            # He's residual-force model re-sticks during slow motion (steps < J), so after a reversal its
            # reference is the last slip, not the turning point; the lower bound above still holds.
            assert travel <= S + max_step + 1e-9
        # nothing moved between the reversal and the breakaway
        assert np.all(mv[r:k] == mv[r])
        jump = direction * (mv[k] - mv[k - 1])
        assert J - 1e-9 <= jump <= J + max_step + 1e-9, f"breakaway jump {jump}, J = {J}"


@settings(max_examples=40, deadline=None)
@given(st.floats(0.5, 8.0), st.floats(0.0, 10.0), st.floats(0.0, 2 * np.pi), st.floats(1.05, 5.0),
       st.sampled_from(["sine", "triangle"]))
def test_choudhury_and_kano_agree_after_first_reversal_on_clean_input(S, J, phase, amp_factor, shape):
    """Same MV from the first breakaway after a reversal that both valves entered moving.

    Before that the two differ only through their start from rest (the literal chart restarts with J and
    then sticks again until S), which no paper fixes.
    """
    A = amp_factor * max(S, J) / 2  # above S/2, and enough to break away in both directions
    n = 8000
    x = np.arange(n) * 2 * np.pi / 1000 + phase
    wave = np.sin(x) if shape == "sine" else 2 / np.pi * np.arcsin(np.sin(x))
    op = 50 + A * wave
    assume(np.all(np.diff(op) != 0))  # clean: never an exactly zero slope
    a = simulate(op, S=S, J=J, model="kano")
    b = simulate(op, S=S, J=J, model="choudhury")
    dop = np.diff(op)
    reversals = np.flatnonzero(np.sign(dop[1:]) != np.sign(dop[:-1])) + 1
    moved_a, moved_b = np.flatnonzero(np.diff(a)) + 1, np.flatnonzero(np.diff(b)) + 1
    assume(moved_a.size and moved_b.size)
    both_moving = max(moved_a[0], moved_b[0])
    later = reversals[reversals > both_moving]
    assume(later.size >= 2)
    r = later[0]
    breakaway = min(moved_a[moved_a > r][0], moved_b[moved_b > r][0])
    assert breakaway < later[1], "no breakaway between two reversals"
    np.testing.assert_array_equal(a[breakaway:], b[breakaway:])


def held_sine(hold=10, n=20000, period=2000, amplitude=10.0):
    k = np.arange(n)
    op = 50 + amplitude * np.sin(2 * np.pi * k / period + 0.3)
    return op[(k // hold) * hold]


def test_held_input_moves_default_valve_and_freezes_literal_chart():
    op = held_sine()
    mv_default = simulate(op, S=5.0, J=2.0)
    assert np.ptp(mv_default) >= 0.5 * np.ptp(op)
    # The literal 2005 flow chart treats each pause as a stop and resets its reference: it never moves.
    mv_literal = simulate(op, S=5.0, J=2.0, model="choudhury")
    assert np.ptp(mv_literal) == 0.0


def test_rest_criterion_makes_held_input_behave_like_the_unheld_signal():
    """OP held for 10 samples, rest criterion 11 samples: exactly the valve driven by one sample per hold."""
    op = held_sine(hold=10)
    per_hold = simulate(op[::10], S=5.0, J=2.0)
    held = simulate(op, S=5.0, J=2.0, rest_samples=11)
    np.testing.assert_array_equal(held[::10], per_hold)
    # the literal model (rest after one unchanged sample) re-sticks at every pause and differs
    literal = simulate(op, S=5.0, J=2.0, rest_samples=1)
    assert np.abs(literal[::10] - per_hold).max() > 1.0
    assert rest_samples_for(1.0, 0.1) == 10
    assert rest_samples_for(0.0, 0.1) == 1
    with pytest.raises(ValueError, match="rest_time"):
        rest_samples_for(-1.0, 0.1)


def test_noisy_input_still_moves_default_valve():
    rng = np.random.default_rng(7)
    n = 20000
    op = 50 + 10 * np.sin(2 * np.pi * np.arange(n) / 2000) + rng.normal(0, 0.5, n)
    mv = simulate(op, S=5.0, J=2.0)
    assert np.ptp(mv) > 0.5 * 20  # travels most of the sine's peak-to-peak


@pytest.mark.parametrize("seed_j, case", [(1.0, "undershoot"), (2.5, "no_offset"), (3.5, "overshoot")])
def test_seed_table1_values_in_seed_form(seed_j, case):
    """Table 1 of Choudhury, Thornhill & Shah (2003), concentration loop, s = 5: j < s/2 undershoot,
    j = s/2 no offset, j > s/2 overshoot."""
    S, J = seed_to_2005(5.0, seed_j)
    assert S == 5.0 and 2 * seed_j == J
    n = 4000
    op = 50 + 10 * np.sin(2 * np.pi * np.arange(n) / 1000 + 0.1)
    mv = simulate(op, S=S, J=J)
    moving = np.flatnonzero(np.diff(mv) != 0) + 1
    moving = moving[moving > 1000]
    rising = moving[np.diff(op)[moving - 1] > 0]
    err = mv[rising] - op[rising]
    if case == "undershoot":
        assert np.all(err < -1.0)  # MV never reaches OP: a permanent offset of (S - J)/2 = 1.5 %
        np.testing.assert_allclose(err, -1.5, atol=1e-9)
    elif case == "no_offset":
        np.testing.assert_allclose(err, 0.0, atol=1e-9)  # tracks OP once moving
    else:
        assert np.all(err > 0.5)  # passes OP: overshoot of (J - S)/2 = 1 %
        np.testing.assert_allclose(err, 1.0, atol=1e-9)


def test_bank_equals_single_valves_and_many_candidates():
    rng = np.random.default_rng(3)
    op = 50 + np.cumsum(rng.normal(0, 0.3, 3000))
    S = np.array([0.0, 1.0, 3.0, 5.0, 5.0])
    J = np.array([0.0, 0.0, 1.5, 2.0, 7.0])
    for model in MODELS:
        many = simulate_many(op, S, J, model=model)
        for i in range(len(S)):
            np.testing.assert_array_equal(many[:, i], simulate(op, S=S[i], J=J[i], model=model))
        bank = StictionBank(len(S), S=S, J=J, model=model)
        bank.reset(op[0])
        stepped = np.array([bank.step(np.full(len(S), u)).copy() for u in op])
        np.testing.assert_array_equal(stepped, many)


def test_scalar_valve_and_parameter_change():
    v = Valve(S=5.0, J=2.0, op0=50.0)
    assert v.mv == pytest.approx(48.5)
    # move up (same direction as the initial rest): breaks after J
    assert v.step(51.0) == pytest.approx(48.5) and v.stuck
    assert v.step(52.5) == pytest.approx(51.0) and not v.stuck
    bank = StictionBank(2, S=5.0, J=2.0)
    bank.set_parameters(S=1.0, index=1)
    np.testing.assert_array_equal(bank.S, [5.0, 1.0])
    with pytest.raises(ValueError, match="S"):
        bank.set_parameters(S=-1.0)
    np.testing.assert_array_equal(bank.S, [5.0, 1.0])  # a refused change changes nothing


def test_no_stiction_is_transparent_and_saturation_holds():
    op = np.linspace(-20, 120, 500)
    for model in ("kano", "he"):
        mv = simulate(op, S=0.0, J=0.0, model=model)
        np.testing.assert_allclose(mv, np.clip(op, 0, 100), atol=1e-12)
    # The literal chart sticks for one sample whenever the slope changes sign, also on leaving a stop at 0 %;
    # elsewhere it is transparent too.
    mv = simulate(op, S=0.0, J=0.0, model="choudhury")
    leaving = np.flatnonzero((op[:-1] <= 0) & (op[1:] > 0)) + 1
    ok = np.ones(op.size, bool)
    ok[leaving] = False
    np.testing.assert_allclose(mv[ok], np.clip(op, 0, 100)[ok], atol=1e-12)


@pytest.mark.parametrize("bad, name", [(np.nan, "op\\[17\\]"), (np.inf, "op\\[17\\]")])
def test_non_finite_op_names_the_sample(bad, name):
    op = np.full(30, 50.0)
    op[17] = bad
    with pytest.raises(ValueError, match=name):
        simulate(op, S=5, J=2)


@pytest.mark.parametrize("kwargs, name", [
    (dict(S=-1.0, J=0.0), "S"),
    (dict(S=1.0, J=-0.5), "J"),
    (dict(S=1.0, J=0.0, model="karnopp"), "model"),
    (dict(S=1.0, J=0.0, rest_samples=0), "rest_samples"),
])
def test_bad_parameters_name_the_parameter(kwargs, name):
    with pytest.raises(ValueError, match=name):
        simulate(np.full(10, 50.0), **kwargs)


@pytest.mark.parametrize("n", [3, 64, 200])
def test_a_bank_refuses_op_of_the_wrong_length_and_keeps_its_state(n):
    # The compiled step has no bounds checks: an op longer than the bank would write past its state.
    bank = StictionBank(n, S=4.0, J=1.0)
    bank.reset(50.0)
    bank.step(np.full(n, 60.0))
    before = bank.mv
    for bad in (np.full(n + 1, 70.0), np.full(n - 1, 70.0), np.full((1, n), 70.0)):
        with pytest.raises(ValueError, match=rf"op must be a scalar or have shape \({n},\)"):
            bank.step(bad)
    for bad in (np.full((5, n + 1), 70.0), np.full((5, n - 1), 70.0), np.full(5 * n, 70.0)):
        with pytest.raises(ValueError, match=rf"op must have shape \(T, {n}\)"):
            bank.run(bad)
    assert np.array_equal(bank.mv, before)
    assert np.array_equal(bank.step(70.0), bank.mv)   # a scalar still drives every valve
