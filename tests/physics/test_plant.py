"""Plant: exact ZOH with fractional dead time against continuous-time references."""
import timeit

import numpy as np
import pytest
import scipy.signal as signal

from valve_emulator.physics.plant import (
    DiscretePlant,
    PlantBank,
    fopdt,
    integrator,
    plant_step_kernel,
    transfer_function_to_zoh,
    transfer_functions_to_zoh,
)

DT = 0.5
SUB = 10  # fine-grid points per sample for the continuous reference; h = DT/SUB = 0.05
H = DT / SUB

# (num, den): first order, second order with a zero, integrator, proper (D != 0), third order.
TFS = {
    "first": ([2.0], [4.0, 1.0]),
    "second_zero": ([1.5, 1.0], [2.0, 0.8, 1.0]),
    "integrator": ([0.7], [1.0, 0.0]),
    "proper": ([2.0, 1.0], [1.0, 3.0]),
    "int_lag": ([1.0], [3.0, 1.0, 0.0]),
}
# Delays on the fine grid: none, an integer multiple of DT, a fractional multiple of DT.
DELAYS = [0.0, 3 * DT, 1.3, 0.05]


def continuous_reference(num, den, delay, du):
    """y(t_k^-) of the continuous TF driven by the ZOH input du_k, delayed by `delay`, via lsim.

    lsim with interp=False is exact for inputs constant between fine-grid points; the delay is a whole
    number of fine steps. lsim returns y(t_j) = C x_j + D u_j (right limit); the left limit replaces
    u_j by u_{j-1}.
    """
    d_h = round(delay / H)
    assert abs(d_h * H - delay) < 1e-12
    T = len(du)
    jj = np.arange(T * SUB + 1)
    src = (jj - d_h) // SUB  # index of the input sample seen at fine point j
    u_fine = np.where(jj - d_h >= 0, du[np.clip(src, 0, T - 1)], 0.0)
    _, y, _ = signal.lsim(signal.lti(num, den), u_fine, jj * H, interp=False)
    _, _, _, D = signal.tf2ss(num, den)
    d = float(np.atleast_2d(D)[0, 0])
    u_prev = np.concatenate([[0.0], u_fine[:-1]])
    y_left = y - d * (u_fine - u_prev)
    return y_left[::SUB][: T + 1]


def simulate(plant: DiscretePlant, u, *, u0=50.0, pv0=0.0):
    bank = PlantBank([plant], u0=u0, pv0=pv0)
    out = [bank.pv[0]]
    for uk in u:
        out.append(bank.step(np.array([uk]))[0])
    return np.array(out)


@pytest.mark.filterwarnings("ignore::scipy.signal.BadCoefficients")
@pytest.mark.parametrize("name", list(TFS))
@pytest.mark.parametrize("delay", DELAYS)
def test_step_response_matches_continuous(name, delay):
    num, den = TFS[name]
    plant = transfer_function_to_zoh(num, den, delay, DT)
    T = 40
    du = np.full(T, 5.0)
    pv = simulate(plant, 50.0 + du, pv0=10.0) - 10.0
    ref = continuous_reference(num, den, delay, du)
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(pv, ref, rtol=0, atol=1e-9 * scale)


def test_first_order_step_matches_analytic_with_fractional_delay():
    K, tau, theta = 2.0, 4.0, 1.3
    plant = transfer_function_to_zoh(*fopdt(K, tau, theta), DT)
    assert (plant.m, round(plant.frac, 12)) == (2, 0.6)
    pv = simulate(plant, np.full(30, 51.0))  # unit step
    t = np.arange(31) * DT
    ref = np.where(t > theta, K * (1.0 - np.exp(-(t - theta) / tau)), 0.0)
    np.testing.assert_allclose(pv, ref, rtol=0, atol=1e-12 * K)


def test_integrator_ramps_with_slope_gain():
    plant = transfer_function_to_zoh(*integrator(0.7, 1.0), DT)
    pv = simulate(plant, np.full(20, 52.0))
    t = np.arange(21) * DT
    np.testing.assert_allclose(pv, 0.7 * 2.0 * np.clip(t - 1.0, 0, None), atol=1e-12)


@pytest.mark.filterwarnings("ignore::scipy.signal.BadCoefficients")
@pytest.mark.parametrize("name", ["second_zero", "proper", "int_lag"])
@pytest.mark.parametrize("delay", [0.0, 1.3])
def test_sine_response_matches_continuous(name, delay):
    num, den = TFS[name]
    plant = transfer_function_to_zoh(num, den, delay, DT)
    t = np.arange(80) * DT
    du = 10.0 * np.sin(0.7 * t + 0.3)
    pv = simulate(plant, 50.0 + du)
    ref = continuous_reference(num, den, delay, du)
    np.testing.assert_allclose(pv, ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))


def test_pure_gain_with_delay_is_a_shifted_copy():
    plant = transfer_function_to_zoh(*fopdt(3.0, 0.0, 2.2), DT)  # m = 4, f = 0.4
    u = 50.0 + np.arange(1.0, 13.0)
    pv = simulate(plant, u)
    # At t_k the delayed input is u(t_k - 2.2) = u_{k-5}.
    expected = np.concatenate([np.zeros(5), 3.0 * (u[:8] - 50.0)])
    np.testing.assert_allclose(pv, expected, atol=1e-12)


def test_delay_close_to_integer_multiple_snaps_to_integer():
    plant = transfer_function_to_zoh([1.0], [1.0, 1.0], 0.3, 0.1)
    assert plant.m == 3 and plant.frac == 0.0
    assert np.all(plant.B0 == 0.0)


MIXED = [
    (TFS["first"], 0.0),
    (TFS["second_zero"], 1.3),
    (TFS["integrator"], 2 * DT),
    (TFS["proper"], 0.05),
    (([4.0], [1.0]), 0.7),  # pure gain
    (TFS["int_lag"], 0.0),
]


def test_bank_of_mixed_plants_equals_each_plant_alone():
    plants = [transfer_function_to_zoh(num, den, d, DT) for (num, den), d in MIXED]
    n = len(plants)
    u0 = np.linspace(40.0, 60.0, n)
    pv0 = np.linspace(-1.0, 3.0, n)
    rng = np.random.default_rng(1)
    U = 50.0 + 10.0 * rng.standard_normal((60, n))
    bank = PlantBank(plants, u0=u0, pv0=pv0)
    bank.reset(u0 + 1.0)
    singles = [PlantBank([p], u0=u0[i], pv0=pv0[i]) for i, p in enumerate(plants)]
    for i, s in enumerate(singles):
        s.reset(u0[i] + 1.0)
    np.testing.assert_array_equal(bank.pv, [s.pv[0] for s in singles])
    for uk in U:
        out = bank.step(uk)
        alone = [s.step(uk[i : i + 1])[0] for i, s in enumerate(singles)]
        assert np.array_equal(out, alone)


def test_reset_gives_steady_state_for_constant_input():
    plants = [transfer_function_to_zoh(num, den, 1.3, DT) for num, den in
              (TFS["first"], TFS["second_zero"], TFS["proper"])]
    gains = np.array([2.0, 1.0, 1.0 / 3.0])  # G(0) = num(0)/den(0)
    bank = PlantBank(plants, u0=50.0, pv0=5.0)
    bank.reset(62.0)
    np.testing.assert_allclose(bank.pv, 5.0 + 12.0 * gains, rtol=1e-12)
    for _ in range(20):
        pv = bank.step(np.full(3, 62.0))
    np.testing.assert_allclose(pv, 5.0 + 12.0 * gains, rtol=1e-12)


def test_reset_of_integrating_plant_starts_at_pv0():
    bank = PlantBank([transfer_function_to_zoh(*integrator(0.5, 1.0), DT)], u0=50.0, pv0=7.0)
    bank.reset(54.0)
    assert bank.pv[0] == 7.0
    # Delay buffer already holds u_init, so the ramp starts at once: slope 0.5 * 4.
    assert bank.step(np.array([54.0]))[0] == pytest.approx(7.0 + 0.5 * 4.0 * DT, abs=1e-12)


def test_returned_pv_is_a_copy_and_property_is_read_only():
    bank = PlantBank([transfer_function_to_zoh(*fopdt(1.0, 1.0, 0.0), DT)], u0=0.0, pv0=0.0)
    first = bank.step(np.array([1.0]))
    saved = first.copy()
    bank.step(np.array([1.0]))
    np.testing.assert_array_equal(first, saved)
    with pytest.raises(ValueError):
        bank.pv[0] = 3.0


def test_non_finite_input_raises_and_changes_nothing():
    plants = [transfer_function_to_zoh(*fopdt(1.0, 2.0, 0.7), DT)] * 3
    bank = PlantBank(plants, u0=50.0, pv0=0.0)
    bank.step(np.array([60.0, 55.0, 40.0]))
    state = [a.copy() for a in bank.kernel_args()]
    with pytest.raises(ValueError, match=r"u\[1\]"):
        bank.step(np.array([60.0, np.nan, 40.0]))
    for before, after in zip(state, bank.kernel_args()):
        np.testing.assert_array_equal(before, after)
    with pytest.raises(ValueError, match="u must have shape"):
        bank.step(np.array([60.0, 55.0]))


@pytest.mark.parametrize(
    "args, name",
    [
        (([1.0, 0.0, 1.0], [1.0, 1.0], 0.0, 1.0), "num"),
        (([1.0], [], 0.0, 1.0), "den"),
        (([1.0], [0.0, 0.0], 0.0, 1.0), "den"),
        (([np.inf], [1.0, 1.0], 0.0, 1.0), "num"),
        (([1.0], [1.0, np.nan], 0.0, 1.0), "den"),
        (([1.0], [1.0, 1.0], -0.1, 1.0), "delay"),
        (([1.0], [1.0, 1.0], np.nan, 1.0), "delay"),
        (([1.0], [1.0, 1.0], 0.0, 0.0), "dt"),
        (([1.0], [1.0, 1.0], 0.0, -1.0), "dt"),
        (([1.0], [1.0, 1.0], 1e9, 1.0), "delay"),
    ],
)
def test_bad_transfer_function_raises_naming_parameter(args, name):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        transfer_function_to_zoh(*args)


def test_many_plants_discretised_at_once_equal_each_alone():
    rng = np.random.default_rng(3)
    names = list(TFS)
    args = [(*TFS[names[i % len(names)]], float(rng.uniform(0.0, 5.0)) * (i % 3 > 0), DT) for i in range(60)]
    args += [([1.0], [tau, 1.0], 0.25, DT) for tau in (1e-3, 0.1, 1e4)] + [([3.0], [1.0], 0.7, DT)]
    batch = transfer_functions_to_zoh(args)
    for a, b in zip(args, batch):
        one = transfer_function_to_zoh(*a)
        for k in ("A", "B0", "B1", "C", "x_rest"):
            np.testing.assert_allclose(getattr(b, k), getattr(one, k), rtol=1e-12, atol=1e-15)
        assert (b.m, b.frac, b.D, b.integrating) == (one.m, one.frac, one.D, one.integrating)
    # First order against its analytic discretisation K(1 - e^{-dt/τ}) (no delay), also for extreme τ.
    for tau in (1e-3, 0.1, 1e4):
        p = transfer_functions_to_zoh([([1.0], [tau, 1.0], 0.0, DT)])[0]
        assert float(p.A[0, 0]) == pytest.approx(np.exp(-DT / tau), rel=1e-12, abs=1e-300)
        assert float(p.C[0] * p.B1[0]) == pytest.approx(-np.expm1(-DT / tau), rel=1e-12)


def test_a_bad_plant_among_many_is_named_by_its_index():
    with pytest.raises(ValueError, match=r"^plant 1: delay must be"):
        transfer_functions_to_zoh([([1.0], [2.0, 1.0], 0.0, 1.0), ([1.0], [2.0, 1.0], -1.0, 1.0)])


def test_bank_rejects_mixed_dt_and_bad_operating_point():
    a = transfer_function_to_zoh([1.0], [1.0, 1.0], 0.0, 1.0)
    b = transfer_function_to_zoh([1.0], [1.0, 1.0], 0.0, 0.5)
    with pytest.raises(ValueError, match="dt"):
        PlantBank([a, b], u0=0.0, pv0=0.0)
    with pytest.raises(ValueError, match="u0"):
        PlantBank([a, a], u0=[1.0, 2.0, 3.0], pv0=0.0)
    with pytest.raises(ValueError, match="pv0"):
        PlantBank([a], u0=0.0, pv0=np.nan)


def test_proper_but_not_strictly_proper_is_allowed():
    plant = transfer_function_to_zoh([2.0, 1.0], [1.0, 3.0], 0.0, DT)
    assert plant.D == 2.0


def test_kernel_can_be_called_directly():
    bank = PlantBank([transfer_function_to_zoh(*fopdt(2.0, 1.0, 0.0), DT)] * 2, u0=0.0, pv0=1.0)
    args = bank.kernel_args()
    assert plant_step_kernel(np.array([1.0, 2.0]), *args) == -1
    np.testing.assert_allclose(bank.pv, 1.0 + 2.0 * np.array([1.0, 2.0]) * (1 - np.exp(-DT)))


def test_step_cost_for_1000_first_order_plants():
    plants = [transfer_function_to_zoh(*fopdt(1.0, 5.0, 1.0), 0.1)] * 1000
    bank = PlantBank(plants, u0=50.0, pv0=0.0)
    u = np.full(1000, 55.0)
    bank.step(u)
    # Best of several repeats is robust to a loaded machine; the target is well under 100 us.
    per_step = min(timeit.repeat(lambda: bank.step(u), number=200, repeat=5)) / 200
    assert per_step < 100e-6


# --- load disturbances and measurement noise (valve_emulator.physics.disturbance) -------------------
from valve_emulator.physics.disturbance import BLOCK, DisturbanceBank, NoiseBank  # noqa: E402

KIND_SET = ["none", "step", "sine", "random_walk", "random_walk"]
PARAMS = dict(amplitude=[0.0, 3.0, 2.0, 0.0, 0.0], time=[0.0, 5.0, 0.0, 0.0, 0.0],
              period=[1.0, 1.0, 8.0, 1.0, 1.0], phase=[0.0, 0.0, 0.5, 0.0, 0.0],
              std=[0.0, 0.0, 0.0, 0.4, 1.5])


def test_deterministic_disturbances_have_known_values():
    bank = DisturbanceBank(KIND_SET, dt=0.5, seed=1, **PARAMS)
    times = np.arange(30) * 0.5
    d = bank.step_many(times)
    np.testing.assert_array_equal(d[:, 0], 0.0)
    np.testing.assert_array_equal(d[:, 1], np.where(times >= 5.0, 3.0, 0.0))
    np.testing.assert_allclose(d[:, 2], 2.0 * np.sin(2 * np.pi * times / 8.0 + 0.5), rtol=1e-14)
    assert d[0, 3] == 0.0 and d[0, 4] == 0.0  # random walks start at zero
    ratio = np.diff(d[:, 4]) / np.diff(d[:, 3])  # different loops draw different normals
    assert not np.allclose(ratio, 1.5 / 0.4)


def test_same_seed_gives_identical_sequences_and_other_seed_differs():
    a = DisturbanceBank(KIND_SET, dt=0.5, seed=7, **PARAMS).step_many(np.arange(600) * 0.5)
    b = DisturbanceBank(KIND_SET, dt=0.5, seed=7, **PARAMS).step_many(np.arange(600) * 0.5)
    c = DisturbanceBank(KIND_SET, dt=0.5, seed=8, **PARAMS).step_many(np.arange(600) * 0.5)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[:, 3], c[:, 3])
    na = NoiseBank([0.1, 0.0, 2.0], 7).step_many(600)
    nb = NoiseBank([0.1, 0.0, 2.0], 7).step_many(600)
    np.testing.assert_array_equal(na, nb)
    np.testing.assert_array_equal(na[:, 1], 0.0)


def test_loop_in_bank_equals_loop_alone_with_same_index():
    steps = 2 * BLOCK + 17  # cross block refills
    times = np.arange(steps) * 0.5
    bank = DisturbanceBank(KIND_SET, dt=0.5, seed=11, **PARAMS).step_many(times)
    noise = NoiseBank([0.3, 1.0, 0.0, 2.0, 0.5], 11).step_many(steps)
    for i, kind in enumerate(KIND_SET):
        single = {k: [v[i]] for k, v in PARAMS.items()}
        alone = DisturbanceBank([kind], dt=0.5, seed=11, index=[i], **single).step_many(times)
        np.testing.assert_array_equal(alone[:, 0], bank[:, i])
        noise_alone = NoiseBank([[0.3, 1.0, 0.0, 2.0, 0.5][i]], 11, index=[i]).step_many(steps)
        np.testing.assert_array_equal(noise_alone[:, 0], noise[:, i])


def test_step_many_equals_repeated_step_and_streams_are_independent():
    times = np.arange(50) * 0.5
    many = DisturbanceBank(KIND_SET, dt=0.5, seed=3, **PARAMS).step_many(times)
    one = DisturbanceBank(KIND_SET, dt=0.5, seed=3, **PARAMS)
    np.testing.assert_array_equal(many, np.array([one.step(t) for t in times]))
    # Disturbance and noise under one seed and index do not reuse the same normals.
    walk = DisturbanceBank(["random_walk"], dt=1.0, seed=3, std=1.0).step_many(np.arange(20.0))
    noise = NoiseBank(1.0, 3).step_many(19)
    assert not np.allclose(np.diff(walk[:, 0]), noise[:, 0])


def test_random_walk_variance_grows_as_std_squared_times_t():
    n, dt, std, steps = 4000, 0.25, 0.8, 64
    bank = DisturbanceBank("random_walk", n=n, dt=dt, seed=5, std=std)
    d = bank.step_many(np.arange(steps + 1) * dt)
    expected = std**2 * steps * dt
    # Sample variance of n independent walks: relative standard error sqrt(2/n) ~ 2.2 %.
    assert np.var(d[-1]) == pytest.approx(expected, rel=0.1)
    noise = NoiseBank(np.full(n, 0.5), 5).step_many(4)
    assert np.std(noise) == pytest.approx(0.5, rel=0.05)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(kinds=["ramp"]), r"kinds\[0\]"),
        (dict(kinds=["sine"], period=0.0), "period"),
        (dict(kinds=["random_walk"], std=-1.0), "std"),
        (dict(kinds=["step"], amplitude=np.nan), "amplitude"),
        (dict(kinds=["step"], seed=-1), "seed"),
        (dict(kinds=["step"], dt=0.0), "dt"),
        (dict(kinds=["step", "none"], index=[0]), "index"),
    ],
)
def test_bad_disturbance_parameters_raise_naming_them(kwargs, name):
    kwargs = {"dt": 0.5, "seed": 1, **kwargs}
    with pytest.raises(ValueError, match=rf"^{name}"):
        DisturbanceBank(kwargs.pop("kinds"), **kwargs)


def test_bad_noise_parameters_raise_naming_them():
    with pytest.raises(ValueError, match="^std"):
        NoiseBank([0.1, -0.1], 1)
    with pytest.raises(ValueError, match="^seed"):
        NoiseBank(0.1, 1.5)


def test_plants_given_as_lists_are_discretised_bit_for_bit_as_when_given_as_arrays():
    # Tuples and lists of numbers take a batched check (10^5 plants of a fleet), arrays the per-plant one:
    # the same normalised coefficients, delay split and matrices, to the last bit, for plants of orders 0..3,
    # integrating ones, integer coefficients, leading zeros, whole and fractional delays.
    rnd = np.random.default_rng(7)
    plants = []
    while len(plants) < 400:
        p = int(rnd.integers(0, 4))
        den = [float(rnd.uniform(0.5, 20))] + [float(rnd.uniform(0.1, 5)) for _ in range(p)]
        if p and rnd.random() < 0.2:
            den[-1] = 0.0   # integrating
        num = [float(rnd.uniform(-5, 5)) for _ in range(int(rnd.integers(1, p + 2)))]
        if rnd.random() < 0.2:
            num = [int(10 * c) or 1 for c in num]
        if rnd.random() < 0.1:
            num = [0.0] + num   # a leading zero: the per-plant path strips it
        delay = float(rnd.choice([0.0, 1.0, 0.3, 0.30000000001, rnd.uniform(0, 20)]))
        dt = float(rnd.choice([0.1, 1.0, 0.05]))
        plants.append((tuple(num) if rnd.random() < 0.5 else num, den, delay, dt))
    as_lists = transfer_functions_to_zoh(plants)
    as_arrays = transfer_functions_to_zoh([(np.array(n, float), np.array(d), t, h) for n, d, t, h in plants])
    for a, b in zip(as_lists, as_arrays):
        for field in ("A", "B0", "B1", "C", "x_rest"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), field
            assert not getattr(a, field).flags.writeable
        assert (a.D, a.m, a.dt, a.frac, a.integrating) == (b.D, b.m, b.dt, b.frac, b.integrating)
    # and one bad plant among good ones is reported with its index, as before
    with pytest.raises(ValueError, match="plant 2: num has non-finite"):
        transfer_functions_to_zoh(plants[:2] + [((1.0, float("nan")), (1.0, 1.0), 0.0, 1.0)])
