"""PI(D) controller bank: textbook steady states, anti-windup, bumpless transfer, bank == singles."""
import math

import numpy as np
import pytest

from valve_emulator.physics.controller import PID, PIDBank, pid_step_kernel
from valve_emulator.physics.plant import PlantBank, fopdt, transfer_function_to_zoh

DT = 0.5


def closed_loop(pid: PIDBank, plant: PlantBank, sp, steps):
    """Run pv_k -> op_k -> pv_{k+1}; return (op, pv) histories."""
    ops, pvs = [], []
    pv = plant.pv.copy()
    for k in range(steps):
        s = sp(k) if callable(sp) else sp
        op = pid.step(np.full(pid.n, s), pv)
        ops.append(op[0])
        pvs.append(pv[0])
        pv = plant.step(op)
    return np.array(ops), np.array(pvs)


def first_order(K=2.0, tau=5.0, delay=0.0, u0=50.0):
    return PlantBank([transfer_function_to_zoh(*fopdt(K, tau, delay), DT)], u0=u0, pv0=0.0)


def test_p_only_offset_equals_textbook_value():
    K, kc, sp = 2.0, 1.5, 10.0
    pid = PIDBank(1, kc=kc, ti=None, bias=50.0, dt=DT)  # bias = u0: zero error at sp = 0
    ops, pvs = closed_loop(pid, first_order(K), sp, 400)
    # pv = K·kc·e and e = sp − pv  =>  e = sp / (1 + K·kc)
    assert sp - pvs[-1] == pytest.approx(sp / (1.0 + K * kc), rel=1e-9)


def test_pi_removes_offset():
    pid = PIDBank(1, kc=1.5, ti=5.0, dt=DT)
    _, pvs = closed_loop(pid, first_order(), 10.0, 600)
    assert abs(10.0 - pvs[-1]) < 1e-8
    assert abs(10.0 - pvs[50]) > 1e-3  # it is the integral that removes it, over time


def test_ti_inf_is_p_only():
    a = PIDBank(1, kc=1.5, ti=math.inf, dt=DT)
    b = PIDBank(1, kc=1.5, ti=None, dt=DT)
    for pv in (0.0, 3.0, -2.0, 7.5):
        assert a.step([10.0], [pv])[0] == b.step([10.0], [pv])[0] == 50.0 + 1.5 * (10.0 - pv)


def windup_prone_pi(kc, ti, bias, sp, plant, steps):
    """Reference PI without anti-windup: the integral always integrates; output clipped."""
    integral, ops = 0.0, []
    pv = plant.pv.copy()
    for k in range(steps):
        e = sp(k) - pv[0]
        integral += DT * e / ti
        op = min(max(bias + kc * (e + integral), 0.0), 100.0)
        ops.append(op)
        pv = plant.step(np.array([op]))
    return np.array(ops)


def test_anti_windup_leaves_limit_within_a_few_samples_of_sign_change():
    kc, ti, switch = 0.8, 4.0, 300
    def sp(k):
        return 150.0 if k < switch else 0.0  # unreachable (pv <= 100), then far below pv
    pid = PIDBank(1, kc=kc, ti=ti, dt=DT)
    ops, pvs = closed_loop(pid, first_order(), sp, switch + 40)
    assert np.all(ops[switch - 100 : switch] == 100.0)  # long saturation
    assert pvs[switch] > 0.0  # the error changes sign at the switch
    leave = switch + int(np.argmax(ops[switch:] < 100.0))
    assert leave - switch <= 3
    wound = windup_prone_pi(kc, ti, 50.0, sp, first_order(), switch + 200)
    stuck = int(np.argmax(wound[switch:] < 100.0))
    assert stuck > 50  # the reference really winds up, so the check above means something


def test_anti_windup_at_lower_limit_too():
    pid = PIDBank(1, kc=1.0, ti=2.0, dt=DT)
    pid.reset(0.0, 0.0)
    for _ in range(200):
        op = pid.step([-100.0], [0.0])  # e = -100: saturate low
    assert op[0] == 0.0
    assert pid.step([1.0], [0.0])[0] > 0.0  # error positive again -> off the limit at once


def test_bumpless_manual_to_auto():
    pid = PIDBank(1, kc=1.2, ti=3.0, td=0.5, dt=DT)
    plant = first_order(delay=1.0)
    closed_loop(pid, plant, 10.0, 40)
    pid.set_manual(0, 30.0)
    pv = plant.pv.copy()
    for _ in range(25):
        op = pid.step([10.0], pv)
        assert op[0] == 30.0
        pv = plant.step(op)
    assert abs(10.0 - pv[0]) > 1.0  # a real error at the switch
    pid.set_auto(0)
    first = pid.step([10.0], pv)[0]
    assert abs(first - 30.0) <= 1e-12
    assert pid.auto[0]
    second = pid.step([10.0], plant.step(np.array([first])))[0]
    assert second != first  # control resumes


def test_bumpless_tuning_change_in_auto():
    pid = PIDBank(1, kc=1.0, ti=4.0, dt=DT)
    e = 2.0
    for _ in range(5):
        op_before = pid.step([e], [0.0])[0]
    pid.set_tuning(0, kc=3.0, ti=8.0)
    op_after = pid.step([e], [0.0])[0]
    # Only the new integral increment kc·dt·e/ti, no proportional jump of (3 - 1)·e.
    assert op_after - op_before == pytest.approx(3.0 * DT * e / 8.0, abs=1e-12)


def test_bumpless_tuning_change_p_only():
    pid = PIDBank(1, kc=1.0, ti=None, dt=DT)
    before = pid.step([4.0], [0.0])[0]
    pid.set_tuning(0, kc=2.5)
    assert pid.step([4.0], [0.0])[0] == pytest.approx(before, abs=1e-12)
    assert pid.step([5.0], [0.0])[0] == pytest.approx(before + 2.5, abs=1e-12)  # new gain acts


def test_direct_and_reverse_action_signs():
    rev = PIDBank(1, kc=2.0, ti=None, dt=DT)
    dirc = PIDBank(1, kc=2.0, ti=None, direct=True, dt=DT)
    assert rev.step([10.0], [13.0])[0] == pytest.approx(50.0 - 6.0)
    assert dirc.step([10.0], [13.0])[0] == pytest.approx(50.0 + 6.0)
    # A direct-acting PI on a negative-gain plant reaches the set point.
    pid = PIDBank(1, kc=1.0, ti=5.0, direct=True, dt=DT)
    _, pvs = closed_loop(pid, first_order(K=-2.0), -10.0, 600)
    assert pvs[-1] == pytest.approx(-10.0, abs=1e-8)


def test_derivative_on_measurement_of_a_ramp():
    kc, td, r = 1.0, 2.0, 0.3
    pid = PIDBank(1, kc=kc, ti=None, td=td, dt=DT)
    for k in range(200):
        pv = r * k * DT
        op = pid.step([0.0], [pv])[0]
    # The filtered derivative of a ramp converges to its slope: D = -r for reverse action.
    assert op == pytest.approx(50.0 + kc * (-pv - td * r), abs=1e-9)


def test_no_derivative_kick_on_set_point_step():
    pid = PIDBank(1, kc=1.0, ti=None, td=5.0, dt=DT)
    pid.step([0.0], [0.0])
    assert pid.step([10.0], [0.0])[0] == pytest.approx(60.0)


def test_reset_starts_at_op0():
    pid = PIDBank(2, kc=[1.0, 2.0], ti=[3.0, None], dt=DT)
    pid.reset([5.0, 5.0], [5.0, 5.0], op0=[20.0, 70.0])
    np.testing.assert_allclose(pid.step([5.0, 5.0], [5.0, 5.0]), [20.0, 70.0], atol=1e-12)


def test_bank_equals_singles():
    params = [
        dict(kc=1.0, ti=3.0, td=0.0, direct=False),
        dict(kc=2.0, ti=None, td=1.0, direct=True),
        dict(kc=0.5, ti=10.0, td=0.4, direct=False),
        dict(kc=3.0, ti=1.0, td=0.0, direct=True),
    ]
    n = len(params)
    bank = PIDBank(n, kc=[p["kc"] for p in params], ti=[p["ti"] for p in params],
                   td=[p["td"] for p in params], direct=[p["direct"] for p in params], dt=DT)
    singles = [PID(**p, dt=DT) for p in params]
    rng = np.random.default_rng(3)
    for k in range(300):
        sp = 10.0 * rng.standard_normal(n)
        pv = 30.0 * rng.standard_normal(n)
        if k == 100:
            bank.set_manual([1, 2], [20.0, 80.0])
            singles[1].set_manual(20.0)
            singles[2].set_manual(80.0)
        if k == 150:
            bank.set_auto(np.array([False, True, True, False]))
            singles[1].set_auto()
            singles[2].set_auto()
        if k == 200:
            bank.set_tuning(3, kc=1.5, ti=2.0)
            singles[3].set_tuning(kc=1.5, ti=2.0)
        out = bank.step(sp, pv)
        assert np.array_equal(out, [s(sp[i], pv[i]) for i, s in enumerate(singles)])


def test_bad_input_raises_and_changes_nothing():
    pid = PIDBank(2, kc=1.0, ti=2.0, dt=DT)
    pid.step([1.0, 2.0], [0.0, 0.0])
    state = [np.copy(a) for a in pid.kernel_args()]
    with pytest.raises(ValueError, match="pv"):
        pid.step([1.0, 2.0], [0.0, np.inf])
    with pytest.raises(ValueError, match="sp"):
        pid.step([np.nan, 2.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="sp must have shape"):
        pid.step([1.0, 2.0, 3.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="op"):
        pid.set_manual(0, 120.0)
    for before, after in zip(state, pid.kernel_args()):
        np.testing.assert_array_equal(before, after)
    assert pid.auto.all()


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(kc=0.0, ti=1.0), "kc"),
        (dict(kc=-1.0, ti=1.0), "kc"),
        (dict(kc=1.0, ti=0.0), "ti"),
        (dict(kc=1.0, ti=-2.0), "ti"),
        (dict(kc=1.0, ti=float("nan")), "ti"),
        (dict(kc=1.0, ti=1.0, td=-1.0), "td"),
        (dict(kc=1.0, ti=1.0, op_min=50.0, op_max=50.0), "op_min"),
        (dict(kc=1.0, ti=1.0, dt=0.0), "dt"),
    ],
)
def test_bad_parameters_raise_naming_them(kwargs, name):
    kwargs = {"dt": DT, **kwargs}
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        PIDBank(1, **kwargs)


def test_bad_tuning_changes_nothing():
    pid = PIDBank(1, kc=1.0, ti=2.0, dt=DT)
    pid.step([3.0], [0.0])
    before = [np.copy(a) for a in pid.kernel_args()]
    with pytest.raises(ValueError, match="^ti"):
        pid.set_tuning(0, kc=2.0, ti=0.0)
    for b, a in zip(before, pid.kernel_args()):
        np.testing.assert_array_equal(b, a)


def test_kernel_can_be_called_directly():
    pid = PIDBank(1, kc=2.0, ti=None, dt=DT)
    assert pid_step_kernel(np.array([3.0]), np.array([1.0]), *pid.kernel_args()) == 0
    assert pid.op[0] == pytest.approx(54.0)
