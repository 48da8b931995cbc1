"""The linear part of the diagnosis: exact recovery of ZOH plants, the batched grid, differences, polish."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.diagnosis.fit.linear import (
    PRIOR_WIDTH,
    LinearStructure,
    delay_grid_sse,
    filter_inputs,
    fit_one,
    highpass,
    input_grid_sse,
    polish,
    prior_term,
)
from valve_emulator.diagnosis.fit.linear_kernels import column_sse
from valve_emulator.physics.plant import PlantBank, transfer_function_to_zoh

DT = 1.0
T = 3000
WINDOW = (60, 2100)


def _input(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 50.0 + np.cumsum(rng.normal(size=T)) * 0.3 + rng.normal(size=T)


def _plant_output(u: np.ndarray, num, den, delay) -> np.ndarray:
    """PV of the physics layer's exact ZOH plant, the recording convention pv_k <- flow up to k-1."""
    bank = PlantBank([transfer_function_to_zoh(num, den, delay, DT)], u0=50.0, pv0=2.0)
    bank.reset(u[0])
    y = np.empty(u.size)
    y[0] = bank.pv[0]
    for k in range(u.size - 1):
        y[k + 1] = bank.step(np.array([u[k]]))[0]
    return y


PLANTS = [
    ((3.0,), (10.0, 1.0), 10.0, LinearStructure(taus=(10.0,), delay=10.0), 3.0),
    ((1.0,), (1.0, 0.0), 3.0, LinearStructure(integrating=True, delay=3.0), 1.0),
    ((2.0,), (15.0, 8.0, 1.0), 4.0, LinearStructure(taus=(5.0, 3.0), delay=4.0), 2.0),
    ((0.5,), (4.0, 1.0, 0.0), 2.0, LinearStructure(taus=(4.0,), integrating=True, delay=2.0), 0.5),
]


@pytest.mark.parametrize("num, den, delay, structure, gain", PLANTS)
def test_exact_structure_replays_a_zoh_plant_exactly(num, den, delay, structure, gain):
    u = _input()
    y = _plant_output(u, num, den, delay)
    fit = fit_one(u, y, WINDOW, structure, DT)
    assert fit.gain == pytest.approx(gain, rel=1e-6)
    y_hat = fit.predict(u, DT)
    scale = np.ptp(y)
    assert np.max(np.abs(y_hat - y)[WINDOW[1]:]) < 1e-5 * scale  # the held-out part too


@pytest.mark.parametrize("structure", [LinearStructure(taus=(7.0,)), LinearStructure(integrating=True),
                                       LinearStructure(taus=(4.0, 2.0)), LinearStructure()])
def test_delay_grid_equals_direct_least_squares(structure):
    rng = np.random.default_rng(3)
    u = rng.normal(size=(5, T))
    y = np.cumsum(rng.normal(size=T)) * 0.1
    delays = np.array([0, 3, 7, 12])
    sse = delay_grid_sse(filter_inputs(u.T, structure, DT), y, WINDOW, delays, structure)
    direct = np.array([[fit_one(u[c], y, WINDOW, LinearStructure(structure.taus, structure.integrating,
                                                                   delay=float(d)), DT).sse
                        for d in delays] for c in range(u.shape[0])])
    np.testing.assert_allclose(sse, direct, rtol=1e-6)


@pytest.mark.parametrize("structure", [LinearStructure(taus=(7.0,)), LinearStructure(integrating=True),
                                       LinearStructure(taus=(4.0, 2.0), integrating=True), LinearStructure()])
@pytest.mark.parametrize("lam", [None, 0.9])
@pytest.mark.parametrize("frac", [0.0, 0.4])
def test_one_pass_from_the_inputs_equals_filtering_then_fitting(structure, lam, frac):
    """The compiled pass that filters while it fits (and its scalar one-column, one-delay form) gives the SSE of
    the explicit route: filter_inputs, highpass, a fractional delay, then least squares per column and delay —
    for 40 columns (split over threads) and for one."""
    rng = np.random.default_rng(5)
    u = 50.0 + np.cumsum(rng.normal(size=(T, 40)), axis=0) * 0.2
    y = np.cumsum(rng.normal(size=T)) * 0.1
    delays = np.array([0, 2, 5, 9])
    z = filter_inputs(u, structure, DT)
    yc = y
    if lam is not None:
        z, yc = highpass(z, lam), highpass(y, lam)
    if frac:
        z = np.vstack([z[:1], (1.0 - frac) * z[1:] + frac * z[:-1]])
    explicit = delay_grid_sse(z, yc, WINDOW, delays, structure, prefiltered=lam is not None)
    fused = input_grid_sse(u, yc, WINDOW, delays, structure, DT, prefilter=lam, frac=frac)
    np.testing.assert_allclose(fused, explicit, rtol=1e-7)
    trend = int(structure.integrating and lam is None)
    one = column_sse(u[:, 7], structure.denominator(DT), structure.integrating, DT, lam, frac, yc, *WINDOW, 5,
                     structure.ntaps, trend)
    assert one == pytest.approx(explicit[7, 2], rel=1e-6)
    if not trend:  # the residual route of fit_one (its ramps' normal equations are ill-conditioned unfiltered)
        st = LinearStructure(structure.taus, structure.integrating, delay=5.0 + frac)
        assert one == pytest.approx(fit_one(u[:, 7], y, WINDOW, st, DT, prefilter=lam).sse, rel=1e-6)


def test_grid_finds_the_true_delay_and_a_constant_column_changes_nothing():
    u = _input(1)
    y = _plant_output(u, (3.0,), (10.0, 1.0), 10.0)
    st = LinearStructure(taus=(10.0,))
    cols = np.column_stack([u, np.full(T, 42.0)])  # a valve that never moves: no information, no blow-up
    sse = delay_grid_sse(filter_inputs(cols, st, DT), y - y.mean(), WINDOW, np.arange(0, 21), st)
    assert int(np.argmin(sse[0])) == 10
    yw = (y - y.mean())[WINDOW[0]:WINDOW[1]]
    baseline = np.sum((yw - yw.mean()) ** 2)
    np.testing.assert_allclose(sse[1], baseline, rtol=1e-9)
    assert np.all(np.isfinite(sse))


@pytest.mark.parametrize("lam", [0.0, 0.95])
def test_prefiltered_fit_is_the_same_model_and_absorbs_the_integrator_trend(lam):
    u = _input(2)
    y = _plant_output(u, (1.0,), (1.0, 0.0), 3.0) + 0.01 * np.arange(T)  # a drifting operating point
    st = LinearStructure(integrating=True, delay=3.0)
    window = (300, 2100)  # after the prefilter's own transient
    fit = fit_one(u, y, window, st, DT, prefilter=lam)
    assert fit.sse < 1e-10 * np.sum(highpass(y, lam)[window[0]:window[1]] ** 2)
    assert fit.gain == pytest.approx(1.0, rel=1e-5)
    z = highpass(filter_inputs(u[:, None], st, DT), lam)
    sse = delay_grid_sse(z, highpass(y, lam), window, np.arange(0, 8), st, prefiltered=True)
    assert int(np.argmin(sse[0])) == 3


def test_highpass_is_the_first_difference_at_lambda_zero():
    x = np.cumsum(np.random.default_rng(7).normal(size=(50, 2)), axis=0)
    np.testing.assert_allclose(highpass(x, 0.0)[1:], np.diff(x, axis=0))


def test_polish_recovers_time_constant_and_fractional_dead_time_from_a_wrong_start():
    u = _input(4)
    y = _plant_output(u, (3.0,), (10.0, 1.0), 10.5) + np.random.default_rng(5).normal(0, 0.05, T)
    start = LinearStructure(taus=(16.0,), delay=12.0)
    fit = polish(u, y, WINDOW, start, DT, free_delay=True, delay_bounds=(0.0, 25.0))
    assert fit.structure.taus[0] == pytest.approx(10.0, rel=0.03)
    assert fit.structure.delay == pytest.approx(10.5, abs=0.15)


def test_polish_prior_decides_between_equivalent_pole_sets():
    # Two real poles are interchangeable; with a prior the one nearer the nominal plant is kept.
    u = _input(6)
    y = _plant_output(u, (1.0,), (32.0, 12.0, 1.0), 2.0)  # (4s+1)(8s+1)
    st = LinearStructure(taus=(3.0, 9.0), delay=2.0)
    fit = polish(u, y, WINDOW, st, DT, free_delay=False, delay_bounds=(0, 10), prior=(4.0, 8.0))
    assert sorted(fit.structure.taus) == pytest.approx([4.0, 8.0], rel=0.02)


def test_the_denominator_is_numpys_polynomial_of_the_poles_bit_for_bit():
    # The polish asks for thousands of denominators, built without np.poly's overhead; the search's answers
    # stay the same only if every coefficient is the same double.
    rng = np.random.default_rng(7)
    for _ in range(3000):
        taus = tuple(float(t) for t in np.exp(rng.uniform(-3.0, 8.0, rng.integers(1, 5))))
        dt = float(rng.choice([0.05, 0.1, 1.0, 2.5]))
        fixed = () if rng.random() < 0.7 else (complex(-0.1, 0.3), complex(-0.1, -0.3))
        poles = [np.exp(-dt / t) for t in taus] + [np.exp(p * dt) for p in fixed]
        got = LinearStructure(taus=taus, fixed_poles=fixed).denominator(dt)
        assert np.array_equal(got, np.real(np.poly(poles))), (taus, dt, fixed)
    assert np.array_equal(LinearStructure().denominator(1.0), np.ones(1))


def test_the_polish_prior_term_is_numpys_sum_bit_for_bit():
    rng = np.random.default_rng(8)
    for n in (1, 2, 3):
        for _ in range(2000):
            x, prior = rng.normal(2.0, 1.5, n), rng.normal(2.0, 1.5, n)
            want = float(np.sum(((np.sort(x) - np.sort(prior)) / PRIOR_WIDTH) ** 2))
            assert prior_term(x, sorted(prior.tolist())) == want


@pytest.mark.parametrize("structure, lam", [
    (LinearStructure(taus=(8.0,)), None),
    (LinearStructure(taus=(12.0, 3.0)), None),
    (LinearStructure(integrating=True), None),
    (LinearStructure(taus=(5.0,), integrating=True), 0.95),
])
def test_a_dead_time_scored_alone_is_its_column_of_the_dead_time_grid_bit_for_bit(structure, lam):
    # The search takes a held dead time's SSE from the grid's column when the grid has been scored anyway.
    rng = np.random.default_rng(11)
    u = np.column_stack([_input(s) for s in range(5)]) + rng.normal(size=(T, 5))
    y = _plant_output(u[:, 0], [1.5], [8.0, 1.0], 4.0) + rng.normal(0.0, 0.1, T)
    y = y if lam is None else highpass(y, lam)
    delays = np.arange(0, 21)
    grid = input_grid_sse(u, y, WINDOW, delays, structure, DT, prefilter=lam)
    for d in (0, 4, 13, 20):
        alone = input_grid_sse(u, y, WINDOW, np.array([d]), structure, DT, prefilter=lam)
        assert np.array_equal(alone[:, 0], grid[:, d])


@pytest.mark.parametrize("structure, lam", [
    (LinearStructure(taus=(8.0,)), None),
    (LinearStructure(taus=(12.0, 3.0)), None),
    (LinearStructure(integrating=True), 0.95),
])
def test_columns_scored_together_score_as_each_column_alone_bit_for_bit(structure, lam):
    # Several columns take their cross terms a tile of samples at a time, a lone column sample by sample; the
    # window leaves a short last tile.
    rng = np.random.default_rng(12)
    u = np.column_stack([_input(s) for s in range(9)]) + rng.normal(size=(T, 9))
    y = _plant_output(u[:, 3], [1.5], [8.0, 1.0], 4.0) + rng.normal(0.0, 0.1, T)
    y = y if lam is None else highpass(y, lam)
    window, delays = (61, 2099), np.arange(0, 31)
    together = input_grid_sse(u, y, window, delays, structure, DT, prefilter=lam)
    for j in range(u.shape[1]):
        alone = input_grid_sse(u[:, j], y, window, delays, structure, DT, prefilter=lam)
        assert alone[0].tobytes() == together[j].tobytes()


def _one_system_sse(G, r, yy, ntaps, sign, held):
    """One system's constrained least-squares SSE as written for one system (the textbook Cholesky, then the
    Lawson–Hanson correction for a gain of the wrong sign or a held gain), in Python floats."""
    q = len(r)
    L = [[0.0] * q for _ in range(q)]
    moves = False
    for i in range(q):
        for j in range(i + 1):
            s = float(G[j, i])
            if i == j:
                s += 1e-10 * (float(G[i, i]) + 1e-300)
            for m in range(j):
                s -= L[i][m] * L[j][m]
            if i == j:
                L[i][i] = float(np.sqrt(s)) if s > 1e-9 * (float(G[i, i]) + 1e-300) else 1e150
                moves = moves or (i < ntaps and L[i][i] != 1e150)
            else:
                L[i][j] = s / L[j][j]
    w = [0.0] * q
    for i in range(q):
        s = float(r[i])
        for m in range(i):
            s -= L[i][m] * w[m]
        w[i] = s / L[i][i]
    beta = [0.0] * q
    for i in range(q - 1, -1, -1):
        s = w[i]
        for m in range(i + 1, q):
            s -= L[m][i] * beta[m]
        beta[i] = s / L[i][i]
    sse = yy
    for i in range(q):
        sse -= beta[i] * float(r[i])
    g = 0.0
    for i in range(ntaps):
        g += beta[i]
    gap = (g - held if moves else 0.0) if held == held else (g if sign * g < 0.0 else 0.0)
    if gap != 0.0:
        cgc = 0.0
        for i in range(q):
            s = 1.0 if i < ntaps else 0.0
            for m in range(i):
                s -= L[i][m] * w[m]
            w[i] = s / L[i][i]
            cgc += w[i] * w[i]
        if cgc > 0.0:
            sse += gap * gap / cgc
    return max(sse, 0.0)


@pytest.mark.parametrize("ntaps,trend", [(1, 0), (1, 1), (2, 1), (3, 0), (4, 1)])
@pytest.mark.parametrize("sign,held", [(0, np.nan), (1, np.nan), (-1, np.nan), (0, 0.7), (1, -0.3)])
def test_systems_solved_side_by_side_score_as_each_system_alone_bit_for_bit(ntaps, trend, sign, held):
    # The grid kernel solves a column's systems (one per dead time) stage by stage over all of them; each SSE
    # must be the one its system gets alone: well-posed systems, a regressor in the span of the others (a valve
    # that never moves: the huge pivot), a column of zeros, NaN, scales far apart.
    from valve_emulator.diagnosis.fit.linear_kernels import _solve_room, _solve_sses

    rng = np.random.default_rng(ntaps * 10 + trend)
    q, n = ntaps + 1 + trend, 40
    G, r = np.zeros((q, q, n)), np.zeros((q, n))
    yy = 0.0
    for k in range(n):
        X = rng.normal(size=(200, q)) * 10.0 ** rng.integers(-6, 7)
        X[:, ntaps] = 1.0
        if k % 7 == 1:
            X[:, 0] = 1.0                   # a tap that never moves: in the span of the offset
        if k % 7 == 2:
            X[:, :ntaps] = 0.0              # every tap zero
        y = X @ rng.normal(size=q) + rng.normal(size=200)
        G[:, :, k], r[:, k] = X.T @ X, X.T @ y
        yy = float(y @ y) if k == 0 else yy
    G[0, 0, 3] = np.nan
    r[0, 5] = np.nan
    out = np.zeros(n)
    _solve_sses(G, r, yy, q, ntaps, float(sign), float(held), _solve_room(q, n), out)
    alone = np.array([_one_system_sse(G[:, :, k], r[:, k], yy, ntaps, sign, held) for k in range(n)])
    assert out.tobytes() == alone.tobytes()


def _column_pass(u, alpha, integ, dt, lam, frac, y, w0, w1, m, ntaps, sign):
    """The column pass written plainly in Python floats: the filter stages sample by sample (the all-pole
    part's past read back from its outputs), the normal equations summed entry by entry in time order."""
    mean = 0.0
    for v in u:
        mean += float(v)
    mean /= u.size
    p, gain = len(alpha) - 1, float(sum(float(a) for a in alpha))
    start = min(max(p, 1), u.size)
    R, Z = [], []
    acc = v0 = hstate = hprev = 0.0
    q = ntaps + 1
    G = [[0.0] * q for _ in range(q)]
    r = [0.0] * q
    yy = 0.0
    for k in range(w1):
        if k < start:
            s = float(u[0]) - mean
        else:
            s = gain * (float(u[k - 1]) - mean)
            for i in range(1, p + 1):
                s -= float(alpha[i]) * R[k - i]
        R.append(s)
        if integ:
            acc += dt * s
            s = acc
        if lam is not None:
            if k == 0:
                v0 = s
            xk = s - v0
            h = xk + hstate
            hstate = -xk + lam * h
            s = h
        if frac > 0.0:
            h = s
            if k > 0:
                s = (1.0 - frac) * h + frac * hprev
            hprev = h
        Z.append(s)
        if k >= w0:
            x = [Z[k - m - i] for i in range(ntaps)] + [1.0]
            yk = float(y[k])
            yy += yk * yk
            for i in range(q):
                r[i] += x[i] * yk
                for jj in range(i, q):
                    G[i][jj] += x[i] * x[jj]
    return _one_system_sse(np.array(G), np.array(r), yy, ntaps, sign, np.nan)


@pytest.mark.parametrize("alpha", [[1.0, -0.9], [1.0, -1.6, 0.66], [1.0, -2.2, 1.6, -0.39], [1.0]])
@pytest.mark.parametrize("m,ntaps,frac", [(0, 1, 0.0), (3, 1, 0.4), (0, 2, 0.0), (2, 2, 0.25)])
@pytest.mark.parametrize("integ,lam", [(False, None), (False, 0.9), (True, 0.95)])
def test_the_polish_pass_is_the_plain_column_pass_bit_for_bit(alpha, m, ntaps, frac, integ, lam):
    # The polish's compiled pass keeps the all-pole part's last outputs and the sums of one or two taps in
    # registers; its SSE must be the plain pass's, every filter stage and dead time.
    rng = np.random.default_rng(len(alpha) * 100 + m * 10 + ntaps)
    u = 50.0 + np.cumsum(rng.normal(size=400)) * 0.3
    y = rng.normal(size=400) + 0.02 * u
    y_cost = y if lam is None else highpass(y, lam)
    for sign in (0, 1, -1):
        got = column_sse(u, np.array(alpha), integ, DT, lam, frac, y_cost, 40, 300, m, ntaps, 0, sign)
        want = _column_pass(u, alpha, integ, DT, lam, frac, y_cost, 40, 300, m, ntaps, sign)
        assert np.float64(got).tobytes() == np.float64(want).tobytes()
