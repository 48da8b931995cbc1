"""Fits that filter their fixed parts once give fit_one's numbers to the bit.

A polish with extra regressors (a disturbance's sinusoid) and an output candidate's grid rows fit the same target
many times: the target and the extra regressors are prefiltered once, the filtered input once per set of poles,
and the normal equations of the columns that do not depend on the poles once per polish
(:class:`~valve_emulator.diagnosis.fit.linear.FixedColumns`). Each must give what fitting from scratch gives,
compared with ``==`` (not a tolerance): the diagnosis' documents are compared at full precision.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.diagnosis.candidates.disturbance import Disturbance
from valve_emulator.diagnosis.fit import linear
from valve_emulator.diagnosis.fit.backfit import Filtered, backfit_sse
from valve_emulator.diagnosis.fit.linear import FixedColumns, LinearStructure, fit_filtered, fit_one, polish
from valve_emulator.diagnosis.fit.linear_kernels import normal_equations, normal_equations_rows

DT = 1.0


def _loop(seed: int, T: int = 900) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flow, a PV that answers it through a lag and a dead time with a sinusoid and noise, and the sinusoid's
    regressors (T, 2)."""
    rng = np.random.default_rng(seed)
    flow = np.cumsum(rng.normal(0.0, 1.0, T))
    k = np.arange(T)
    basis = np.column_stack([np.sin(2 * np.pi * k / 57.0), np.cos(2 * np.pi * k / 57.0)])
    y = np.zeros(T)
    for i in range(4, T):
        y[i] = 0.9 * y[i - 1] + 0.1 * flow[i - 4]
    y = y + basis @ np.array([0.7, -0.3]) + rng.normal(0.0, 0.05, T)
    return flow, y, basis


STRUCTURES = [
    LinearStructure(taus=(8.0,), delay=3.0),
    LinearStructure(taus=(8.0,), delay=3.4),                       # a fractional dead time
    LinearStructure(taus=(6.0, 2.5), delay=1.0),                   # two taps
    LinearStructure(integrating=True, delay=2.0),                  # the ramp (no prefilter)
    LinearStructure(taus=(8.0,), delay=3.0, sign=-1),              # the sign forbids this gain: held at 0
    LinearStructure(taus=(8.0,), delay=3.0, gain=0.25),            # a held gain
]


def test_normal_equations_rows_completes_the_same_bits():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(500, 6))
    y = rng.normal(size=500)
    G0, b0 = normal_equations(X, y)
    for rows in (1, 2, 3):
        old = X.copy()
        old[:, :rows] = rng.normal(size=(500, rows))      # the fixed columns' entries come from another matrix
        G, b = normal_equations(old, y)
        normal_equations_rows(X, y, rows, G, b)
        assert np.array_equal(G, G0) and np.array_equal(b, b0)


@pytest.mark.parametrize("prefilter", [None, 0.9])
@pytest.mark.parametrize("st", STRUCTURES, ids=lambda s: f"{s.taus}-{s.integrating}-{s.delay}-{s.sign}-{s.gain}")
def test_fixed_columns_give_fit_one_sse(st, prefilter):
    flow, y, extra = _loop(1)
    window = (40, 900)
    y_cost = y if prefilter is None else linear.highpass(y, prefilter)
    extra_cost = extra if prefilter is None else linear.highpass(extra, prefilter)
    fixed = FixedColumns(y_cost, window, st.ntaps, st.integrating and prefilter is None, extra_cost)
    for delay in (st.delay, st.delay + 1.7, 0.0):        # one instance, many evaluations
        s = replace(st, delay=delay)
        z = linear.filter_inputs(flow, s, DT)
        z = z if prefilter is None else linear.highpass(z, prefilter)
        want = fit_one(flow, y, window, s, DT, prefilter=prefilter, extra=extra).sse
        assert fixed.sse(z, s, DT) == want
        assert fit_filtered(z, y_cost, window, s, DT, prefiltered=prefilter is not None, extra=extra_cost).sse == want


POLISHED = [  # (structure, with the extra regressors): the polishes that fit_one serves
    (LinearStructure(taus=(5.0,), delay=2.0), True),
    (LinearStructure(taus=(5.0, 1.5), delay=2.0), True),
    (LinearStructure(taus=(5.0,), integrating=True, delay=2.0), False),   # the ramp without a prefilter
    (LinearStructure(taus=(5.0,), delay=2.0, gain=0.5), False),
]


@pytest.mark.parametrize("prefilter", [None, 0.8])
@pytest.mark.parametrize("st, with_extra", POLISHED, ids=["extra", "extra-2taps", "integrating", "held-gain"])
def test_polish_visits_what_fit_one_from_scratch_visits(st, with_extra, prefilter, monkeypatch):
    """A polish that fit_one serves (extra regressors, an integrator's ramp, a held gain) ends where one whose
    every evaluation fits from scratch ends: the same structure and SSE, to the bit (the same costs, so the same
    simplex steps)."""
    flow, y, extra = _loop(2)
    window = (40, 900)
    kw = dict(free_delay=True, delay_bounds=(0.0, 10.0), prefilter=prefilter, extra=extra if with_extra else None,
              max_evals=60)
    got = polish(flow, y, window, st, DT, **kw)

    class FromScratch:
        def __init__(self, y, window, ntaps, trend, extra):
            self.y, self.window, self.extra = y, window, extra

        def sse(self, z, structure, dt):
            return fit_filtered(z, self.y, self.window, structure, dt, prefiltered=prefilter is not None,
                                extra=self.extra).sse

    monkeypatch.setattr(linear, "FixedColumns", FromScratch)
    want = polish(flow, y, window, st, DT, **kw)
    assert got.structure == want.structure and got.sse == want.sse
    assert got.structure != st                              # it moved: the evaluations were compared


def _reference_backfit_sse(flow, y, window, st, dt, extra, prefilter, delays) -> float:
    """The quick backfit's SSE with extra regressors as written before the rows shared their filtering: the
    dead time chosen on the filtered flow and target cleared of the regressors, then fit_one from scratch."""
    z = linear.filter_inputs(flow[:, None], st, dt)
    target, ex = y, extra
    if prefilter is not None:
        z, target, ex = linear.highpass(z, prefilter), linear.highpass(y, prefilter), linear.highpass(extra, prefilter)
    clear = lambda x: x - ex @ np.linalg.lstsq(ex, x, rcond=None)[0]  # noqa: E731
    sse = linear.delay_grid_sse(clear(z), clear(target), window, delays, st, prefiltered=prefilter is not None)[0]
    best = replace(st, delay=float(delays[int(np.argmin(sse))]) * dt)
    return fit_one(flow, y, window, best, dt, prefilter=prefilter, extra=extra).sse


@pytest.mark.parametrize("prefilter", [None, 0.9])
def test_output_rows_sharing_their_filtering_score_as_alone(prefilter):
    """A disturbance's grid rows scored with one shared :class:`Filtered` (the dead time re-chosen per row) score
    what the backfit scored from scratch, and a Filtered made for other poles is not used."""
    flow, y, _ = _loop(4)
    window = (40, flow.size)
    st = LinearStructure(taus=(8.0,), delay=3.0)
    ctx = ChainContext(dt=DT, op=flow, op_span=100.0, pv=y, window=window)
    cand = Disturbance()
    delays = np.arange(0, 8)
    shared = Filtered(flow, y, st, DT, prefilter)
    stale = Filtered(flow, y, replace(st, taus=(3.0,)), DT, prefilter)
    for period in (57.0, 40.0, 90.0):
        row = np.array([period, 0.0, 0.0])
        extra = cand.regressors(row, ctx)
        want = _reference_backfit_sse(flow, y, window, st, DT, extra, prefilter, delays)
        for filtered in (None, shared, stale):
            assert backfit_sse(flow, y, window, st, DT, cand, row, ctx, prefilter=prefilter, delays=delays,
                               filtered=filtered) == want


@pytest.mark.parametrize("st", STRUCTURES[:4], ids=["lag", "fractional", "two-lags", "integrating"])
def test_filter_inputs_given_its_own_mean(st):
    """The input's mean computed once (as filter_inputs computes it) filters to the same bits as leaving it
    to filter_inputs at every call."""
    flow, _, _ = _loop(5)
    level = float(np.asarray(flow, dtype=np.float64)[:, None].mean(axis=0)[0])
    assert np.array_equal(linear.filter_inputs(flow, st, DT, mean=level), linear.filter_inputs(flow, st, DT))


ONE_COLUMN = [  # structures whose polish takes sse_one's compiled pass at every evaluation (OneColumn.serves)
    LinearStructure(taus=(5.0,), delay=2.0),
    LinearStructure(taus=(5.0, 1.5), delay=2.0),
    LinearStructure(taus=(5.0,), delay=2.0, sign=-1),              # the sign forbids the free gain
    LinearStructure(taus=(5.0,), delay=2.0, taus_held=True),       # only the dead time searched
]


@pytest.mark.parametrize("prefilter", [None, 0.8])
@pytest.mark.parametrize("st", ONE_COLUMN, ids=["lag", "two-lags", "sign", "taus-held"])
def test_one_column_gives_sse_one(st, prefilter):
    """:class:`~valve_emulator.diagnosis.fit.linear.OneColumn` prepared once gives sse_one's SSE to the bit for
    other time constants and dead times (fractional ones too), and None exactly where sse_one fits from scratch
    (a dead time that leaves the window's first samples without a regressor)."""
    flow, y, _ = _loop(6)
    window = (6, 900)
    y_cost = y if prefilter is None else linear.highpass(y, prefilter)
    assert linear.OneColumn.serves(st, prefilter)
    one = linear.OneColumn(flow, y_cost, window, st, DT, prefilter)
    scratch = 0
    for factor in (1.0, 0.37, 2.9):
        taus = tuple(t * factor for t in st.taus)
        for delay in (0.0, 2.0, 3.45, 5.999, 7.2):
            s = replace(st, taus=taus, delay=delay)
            got = one.sse(taus, delay)
            want = linear.sse_one(flow, y, window, s, DT, prefilter=prefilter)
            m, _ = linear.split_delay(delay / DT)
            if window[0] < m + s.ntaps:
                assert got is None
                scratch += 1
            else:
                assert got == want
    assert scratch                                      # the fallback was met too


@pytest.mark.parametrize("st", [LinearStructure(taus=(5.0,), delay=2.0, gain=0.5),
                                LinearStructure(integrating=True, delay=2.0),
                                LinearStructure(taus=(5.0,), fixed_poles=(-0.2 + 0.3j, -0.2 - 0.3j), delay=2.0)],
                         ids=["held-gain", "integrating-ramp", "fixed-poles"])
def test_one_column_serves_only_the_compiled_pass(st):
    assert not linear.OneColumn.serves(st, None)


@pytest.mark.parametrize("prefilter", [None, 0.8])
@pytest.mark.parametrize("st", ONE_COLUMN[:2], ids=["lag", "two-lags"])
def test_polish_through_one_column_visits_what_sse_one_visits(st, prefilter, monkeypatch):
    """A polish whose evaluations go through OneColumn ends where one that builds each structure and calls
    sse_one ends: the same structure and SSE, to the bit."""
    flow, y, _ = _loop(7)
    window = (40, 900)
    kw = dict(free_delay=True, delay_bounds=(0.0, 10.0), prefilter=prefilter, max_evals=60)
    got = polish(flow, y, window, st, DT, **kw)
    monkeypatch.setattr(linear.OneColumn, "serves", staticmethod(lambda structure, prefilter: False))
    want = polish(flow, y, window, st, DT, **kw)
    assert got.structure == want.structure and got.sse == want.sse and np.array_equal(got.taps, want.taps)
    assert got.structure != st


def _whole_record_design(z: np.ndarray, delay: float, ntaps: int, trend: bool, extra) -> np.ndarray:
    """The module docstring's regressors over the whole record, spelled out here: taps ``z_{k-d-j}`` (the first
    sample held before the record starts, a shift below zero taken as none, a fractional ``d = m + f``
    interpolated as ``(1 - f) a + f b``), an offset, a ramp ``k/T`` when ``trend``, and ``extra``."""
    T = z.shape[0]
    m = int(np.floor(delay + 1e-9))
    f = max(0.0, delay - m)
    k = np.arange(T)
    taps = []
    for j in range(ntaps):
        col = z[np.clip(k - max(m + j, 0), 0, None)]
        if f > 0.0:
            col = (1.0 - f) * col + f * z[np.clip(k - max(m + j + 1, 0), 0, None)]
        taps.append(col)
    cols = [np.column_stack(taps), np.ones((T, 1))] + ([(k / T)[:, None]] if trend else [])
    return np.hstack(cols + ([] if extra is None else [np.asarray(extra, dtype=float).reshape(T, -1)]))


@pytest.mark.parametrize("trend", [False, True])
@pytest.mark.parametrize("ntaps", [1, 2, 3])
def test_window_design_is_the_whole_records_regressors_on_the_window(trend, ntaps):
    # fit_filtered and FixedColumns lay out the window's rows only: every entry must be the one the whole record's
    # regressors hold there, to the bit (-0.0 included), for whole, fractional, zero, negative and long dead times,
    # windows that start before the dead time's first sample or at the record's start, with and without extra.
    rng = np.random.default_rng(5)
    for T in (7, 60, 400):
        z = rng.normal(size=T)
        z[T // 3] = -0.0
        for delay in (0.0, 0.4, 1.0, 2.7, 9.0, 41.5, 500.0, -1.0):
            for w0, w1 in ((0, T), (2, T), (T // 2, T - 1), (1, 2)):
                for extra in (None, rng.normal(size=(T, 2)), rng.normal(size=T)):
                    whole = _whole_record_design(z, delay, ntaps, trend, extra)[w0:w1]
                    window = linear._window_design(z, delay, ntaps, (w0, w1), trend, extra)
                    assert np.array_equal(linear.delayed_regressors(z, delay, ntaps)[w0:w1], whole[:, :ntaps])
                    assert window.shape == whole.shape and window.flags.c_contiguous
                    assert np.ascontiguousarray(whole).view(np.uint64).tolist() == window.view(np.uint64).tolist()
