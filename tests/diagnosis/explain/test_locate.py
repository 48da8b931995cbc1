"""Locating a residual in time and operating conditions; profile intervals; the fit measure; data checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from valve_emulator.diagnosis.explain.locate import SHARE, condition_masks, energy_windows, locate
from valve_emulator.diagnosis.fit.data import fit_percent, prepare
from valve_emulator.diagnosis.fit.uncertainty import intervals
from valve_emulator.recordings.recording import Recording, RecordingError

DT = 1.0


def _triangle(n: int, period: int, amp: float = 5.0) -> np.ndarray:
    phase = (np.arange(n) % period) / period
    return 50.0 + amp * (4 * np.abs(phase - 0.5) - 1)


def test_windows_find_bursts_and_hold_the_stated_share():
    t = np.arange(3000) * DT
    rng = np.random.default_rng(0)
    energy = rng.uniform(0.0, 0.01, t.size)
    bursts = [(500, 560), (1500, 2040), (2400, 2450)]  # one long, evenly high stretch among them
    for a, b in bursts:
        energy[a:b] += 1.0
    windows, mask = energy_windows(t, energy, 10)
    assert len(windows) == 3
    for (a, b), (wa, wb) in zip(bursts, windows):
        assert wa <= t[a] + 10 and wb >= t[b - 1] - 10  # each burst is covered (smoothing blurs the edges)
        assert wb - wa < (b - a) + 30
    assert energy[mask].sum() >= SHARE * energy.sum()


def test_reversals_of_a_noisy_triangle_are_found_after_each_turning_point():
    op = _triangle(2000, 200) + np.random.default_rng(1).normal(0.0, 0.05, 2000)
    masks = condition_masks(op, w=5, horizon=20)
    rev = masks["after OP reversals"]
    starts = np.flatnonzero(np.diff(rev.astype(int)) == 1) + 1
    turning = np.arange(100, 2000, 100)  # extremes of the triangle (every half period)
    assert len(starts) >= len(turning) - 1
    assert all(np.min(np.abs(turning - s)) <= 6 for s in starts)
    assert 0.15 < rev.mean() < 0.25  # 20 samples after each of 19-20 turns


def test_residual_after_reversals_is_attributed_to_reversals():
    n = 3000
    op = _triangle(n, 300)
    t = np.arange(n) * DT
    energy = np.full(n, 0.01)
    for k in range(150, n, 150):  # a burst right after each turning point, as stiction leaves
        energy[k:k + 20] += 1.0
    loc = locate(t, op, energy, dt=DT, response_time=30.0)
    assert loc.strongest.condition.startswith("within 30 s after OP reversals")
    assert loc.strongest.lift > 3.0
    level = locate(t, op, (op - 50.0).clip(0) ** 2, dt=DT, response_time=30.0)  # grows with OP level
    assert level.strongest.condition == "at high OP"


def test_profile_interval_matches_the_chi_square_contour_of_a_parabola():
    # N ln(SSE/SSE_min) = ((S - 5)/0.1)^2 exactly: the 95 % interval is 5 ± 0.1·sqrt(3.84)
    S = np.linspace(4.5, 5.5, 2001)
    n = 1000
    sse = np.exp(((S - 5.0) / 0.1) ** 2 / n)
    lo, hi = intervals(S[:, None], sse, n, ("S",), 1)["S"]
    half = 0.1 * np.sqrt(chi2.ppf(0.95, 1))
    assert lo == pytest.approx(5.0 - half, abs=1e-3) and hi == pytest.approx(5.0 + half, abs=1e-3)


def test_fit_percent():
    y = np.sin(np.linspace(0, 10, 500))
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0, abs=1e-12)
    assert fit_percent(y, 2 * y - y.mean()) == pytest.approx(0.0, abs=1e-9)


def _rec(n: int, **over) -> Recording:
    t = np.arange(n) * DT
    cols = {"op": 50 + np.sin(t / 10), "pv": np.cos(t / 10)}
    cols.update(over)
    return Recording(t, None, cols["op"], None, cols["pv"], source="mem.csv")


def test_prepare_needs_enough_samples_and_names_the_line():
    too_short = r"mem\.csv: line 151: 150 data row\(s\), the diagnosis needs at least 200"
    with pytest.raises(RecordingError, match=too_short):
        prepare(_rec(150))
    with pytest.raises(RecordingError, match="needs at least 610"):  # dead times up to 30 + 30 samples
        prepare(_rec(400), nominal_delay=30.0)
    p = prepare(_rec(1000))
    assert p.train[1] == 700 and p.test == (700, 1000) and p.train[0] >= 50


def test_prepare_rejects_constant_and_non_finite_signals():
    with pytest.raises(RecordingError, match="column 'op' is constant"):
        prepare(_rec(1000, op=np.full(1000, 40.0)))
    pv = np.cos(np.arange(1000) / 10.0)
    pv[17] = np.nan
    with pytest.raises(RecordingError, match="line 19, column 'pv': nan is not a finite number"):
        prepare(_rec(1000, pv=pv))
