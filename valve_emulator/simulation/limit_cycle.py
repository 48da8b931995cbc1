r"""Limit cycles: measure them in a signal, and predict them by harmonic balance.

Prediction
----------
With the valve input ``OP = A sin(wt)`` the stiction block is replaced by its describing function
``N(A)`` (:mod:`valve_emulator.physics.describing_function`) and the rest of the loop, seen from MV back to
OP, by its frequency response

.. math::

    L(j\omega) = \sigma\, k_f\, C(j\omega)\, G(j\omega), \qquad
    C(s) = k_c\Big(1 + \frac{1}{T_i s} + \frac{T_d s}{1 + T_d s / N_d}\Big), \qquad
    G(s) = \frac{\mathrm{num}(s)}{\mathrm{den}(s)} e^{-\theta s},

where ``k_f`` is the local slope of the flow characteristic (``characteristic_gain``) and ``sigma = +1``
for reverse action (``e = sp - pv``: with a positive process gain this is negative feedback with loop
gain ``+C G`` as written) and ``-1`` for direct action. A limit cycle ``(A, w)`` solves

.. math:: 1 + N(A) L(j\omega) = 0 \iff L(j\omega) = -1/N(A).

We solve ``r(u, v) = \log(-N(A) L(j\omega)) = 0`` (real and imaginary part: log-magnitude and phase
mismatch) in ``u = \log(A - S/2)``, ``v = \log\omega``: a grid scan over both marks the cells where both
parts change sign (phase within +-90 deg, away from the branch cut), and ``scipy.optimize.root`` refines
each. ``log(A - S/2)`` instead of ``log A`` keeps amplitudes just above the threshold ``S/2`` (where ``N``
changes fastest) resolvable. The controller's derivative is filtered as in
:mod:`valve_emulator.physics.controller` unless ``derivative_filter=None``.

Stability (Loeb's criterion, see e.g. Atherton, *Nonlinear Control Engineering*, 1975; derived here): with
``F(A, s) = 1 + N(A) L(s)``, perturb the amplitude by ``dA``; the root ``s = alpha + j w`` moves by
``ds = -(F_A / F_s) dA`` with ``F_s = -j F_w`` (``F`` is analytic in ``s``). The cycle is stable when a
larger amplitude decays (``Re ds < 0``), i.e. when ``U_A V_w - U_w V_A > 0`` for ``F = U + jV``. The same
sign follows from ``r`` (``r = log(1 - F)``) and the log variables (positive
factors), so a solution is stable when ``det(dr/d(u, v)) > 0``.

When several stable solutions exist the one with the smallest amplitude is returned: a loop that starts
near rest grows into that one first. ``found`` is False when no *stable* solution exists (unstable ones,
which are never observed, are still listed in ``Prediction.solutions``). The method is approximate: the
describing function assumes the valve input is a sine, so predictions are good when the loop filters
harmonics (the integrating level loop of Choudhury, Thornhill & Shah, ~10 % in period) and rough when OP
is a ramp (their concentration loop).

Measurement
-----------
:func:`measure_limit_cycle` looks at the last part of a signal; see its docstring for the criteria.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import optimize

from valve_emulator.physics.controller import DERIVATIVE_FILTER
from valve_emulator.physics.describing_function import describing_function

__all__ = [
    "LimitCycle",
    "Prediction",
    "HarmonicBalanceSolution",
    "measure_limit_cycle",
    "predict_limit_cycle",
    "loop_frequency_response",
]


# ------------------------------------------------------------------------------------------ measurement

@dataclass(frozen=True)
class LimitCycle:
    """A measured oscillation: half peak-to-peak ``amplitude``, ``period`` (s, NaN if < 1 cycle),
    ``sustained`` (see :func:`measure_limit_cycle`), ``n_cycles`` whole cycles seen, ``level`` (mean)."""

    amplitude: float
    period: float
    sustained: bool
    n_cycles: int
    level: float = math.nan


def _upward_crossings(x: np.ndarray, level: float, h: float) -> np.ndarray:
    """Sample indices ``j`` such that the mean is crossed upwards between ``j`` and ``j + 1``.

    A Schmitt trigger with band ``level +- h`` decides which crossings count, so noise around the mean does
    not make extra cycles; within each counted rise the last crossing of ``level`` itself is taken.
    """
    hi = x > level + h
    lo = x < level - h
    idx = np.flatnonzero(hi | lo)
    if idx.size < 2:
        return np.empty(0, dtype=np.int64)
    state = hi[idx]
    rises = np.flatnonzero(state[1:] & ~state[:-1]) + 1
    out = []
    for p in rises:
        i_b, i_a = idx[p - 1], idx[p]
        seg = x[i_b:i_a + 1]
        j = np.flatnonzero((seg[:-1] < level) & (seg[1:] >= level))[-1]
        out.append(i_b + j)
    return np.asarray(out, dtype=np.int64)


def measure_limit_cycle(t: ArrayLike, x: ArrayLike, *, last_fraction: float = 0.5, hysteresis: float = 0.1,
                        decay_tolerance: float = 0.2, rel_tolerance: float = 1e-3,
                        abs_tolerance: float = 1e-9) -> LimitCycle:
    """Amplitude, period and persistence of the oscillation in the last part of ``x(t)``.

    Parameters
    ----------
    t, x : 1-D arrays of the same length; ``t`` strictly increasing, both finite.
    last_fraction : the window is the last ``last_fraction`` of the time span (0 < f <= 1), so that the
        start-up transient is left out.
    hysteresis : half-width of the crossing band as a fraction of the window's half range.
    decay_tolerance, rel_tolerance, abs_tolerance : thresholds of the ``sustained`` test below.

    Returns
    -------
    LimitCycle
        * cycles run between consecutive upward crossings of the window mean ``level`` (interpolated
          linearly between samples, counted with a Schmitt trigger of band ``+- hysteresis * half range``);
        * ``period`` = median cycle duration; ``amplitude`` = median over cycles of half the peak-to-peak
          within the cycle (half the window's range when there is no whole cycle);
        * ``sustained`` is True when there are at least 2 whole cycles, ``amplitude > rel_tolerance *
          |level| + abs_tolerance`` (an oscillation that is visible against the signal level), and the
          oscillation is not decaying: the median amplitude of the later half of the cycles is at least
          ``(1 - decay_tolerance)`` times that of the earlier half. A growing oscillation counts as
          sustained.
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if t.ndim != 1 or x.shape != t.shape:
        raise ValueError(f"t and x must be 1-D of the same length, got shapes {t.shape} and {x.shape}")
    if t.size < 2:
        raise ValueError(f"t must have at least 2 samples, got {t.size}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
        raise ValueError("t and x must be finite")
    if np.any(np.diff(t) <= 0):
        raise ValueError("t must be strictly increasing")
    if not 0.0 < last_fraction <= 1.0:
        raise ValueError(f"last_fraction must be in (0, 1], got {last_fraction!r}")
    if not 0.0 <= hysteresis < 1.0:
        raise ValueError(f"hysteresis must be in [0, 1), got {hysteresis!r}")
    start = t[-1] - last_fraction * (t[-1] - t[0])
    w = t >= start
    tw, xw = t[w], x[w]
    level = float(np.mean(xw))
    half_range = 0.5 * float(np.max(xw) - np.min(xw))
    idx = _upward_crossings(xw, level, hysteresis * half_range) if half_range > 0 else np.empty(0, int)
    n_cycles = max(int(idx.size) - 1, 0)
    if n_cycles == 0:
        return LimitCycle(half_range, math.nan, False, 0, level)
    # Crossing instants between samples j and j + 1, by linear interpolation.
    frac = (level - xw[idx]) / (xw[idx + 1] - xw[idx])
    tc = tw[idx] + frac * (tw[idx + 1] - tw[idx])
    amps = np.array([0.5 * (np.max(xw[a:b + 2]) - np.min(xw[a:b + 2])) for a, b in zip(idx[:-1], idx[1:])])
    amplitude = float(np.median(amps))
    period = float(np.median(np.diff(tc)))
    sustained = False
    if n_cycles >= 2:
        half = n_cycles // 2
        decaying = np.median(amps[n_cycles - half:]) < (1 - decay_tolerance) * np.median(amps[:half])
        sustained = amplitude > rel_tolerance * abs(level) + abs_tolerance and not decaying
    return LimitCycle(amplitude, period, bool(sustained), n_cycles, level)


# ------------------------------------------------------------------------------------------- prediction

@dataclass(frozen=True)
class HarmonicBalanceSolution:
    """One solution of ``1 + N(A) L(jw) = 0``: OP amplitude (% travel), ``omega`` (rad/s), stability."""

    amplitude: float
    omega: float
    stable: bool

    @property
    def period(self) -> float:
        return 2 * math.pi / self.omega


@dataclass(frozen=True)
class Prediction:
    """Predicted limit cycle: OP ``amplitude`` (% travel), ``period`` (s), ``omega`` (rad/s); NaN and
    ``found=False`` when no stable solution exists. ``solutions`` lists every solution found."""

    amplitude: float
    period: float
    omega: float
    found: bool
    solutions: tuple[HarmonicBalanceSolution, ...] = ()


def _controller_terms(controller: Any) -> tuple[float, float | None, float, str]:
    """``(kc, ti, td, action)`` from a ControllerConfig-like object or a 4-tuple."""
    if hasattr(controller, "kc"):
        kc, ti, td, action = controller.kc, controller.ti, controller.td, controller.action
    else:
        kc, ti, td, action = controller
    kc = float(kc)
    if not math.isfinite(kc) or kc <= 0:
        raise ValueError(f"controller.kc must be > 0, got {kc!r}")
    if ti is not None:
        ti = float(ti)
        if math.isnan(ti) or ti <= 0:
            raise ValueError(f"controller.ti must be > 0, or None/inf for no integral action, got {ti!r}")
    td = 0.0 if td is None else float(td)
    if not math.isfinite(td) or td < 0:
        raise ValueError(f"controller.td must be >= 0, got {td!r}")
    if action not in ("reverse", "direct"):
        raise ValueError(f"controller.action must be 'reverse' or 'direct', got {action!r}")
    return kc, ti, td, action


def _plant_terms(plant: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """``(num, den, delay)`` from a PlantConfig-like object or a 3-tuple."""
    if hasattr(plant, "num"):
        num, den, delay = plant.num, plant.den, plant.delay
    else:
        num, den, delay = plant
    num = np.atleast_1d(np.asarray(num, dtype=float))
    den = np.atleast_1d(np.asarray(den, dtype=float))
    for name, c in (("num", num), ("den", den)):
        if c.ndim != 1 or not np.all(np.isfinite(c)) or not np.any(c):
            raise ValueError(f"plant.{name} must be finite polynomial coefficients, not all zero, got {c!r}")
    delay = float(delay)
    if not math.isfinite(delay) or delay < 0:
        raise ValueError(f"plant.delay must be >= 0, got {delay!r}")
    return num, den, delay


def loop_frequency_response(omega: ArrayLike, controller: Any, plant: Any, *,
                            characteristic_gain: float = 1.0,
                            derivative_filter: float | None = DERIVATIVE_FILTER) -> np.ndarray:
    """``L(jw) = sigma k_f C(jw) G(jw)``, the loop from MV back to OP (see the module docstring).

    ``controller``: an object with ``kc, ti, td, action`` (e.g. ``ControllerConfig``) or that 4-tuple;
    ``ti`` None/inf means no integral action. ``plant``: an object with ``num, den, delay`` (e.g.
    ``PlantConfig``) or that 3-tuple, coefficients highest power first. ``derivative_filter`` is ``N_d``
    (None: ideal derivative ``T_d s``).
    """
    kc, ti, td, action = _controller_terms(controller)
    num, den, delay = _plant_terms(plant)
    s = 1j * np.asarray(omega, dtype=float)
    c = np.ones_like(s)
    if ti is not None and math.isfinite(ti):
        c = c + 1.0 / (ti * s)
    if td > 0:
        c = c + (td * s if derivative_filter is None else td * s / (1 + td * s / derivative_filter))
    g = np.polyval(num, s) / np.polyval(den, s) * np.exp(-delay * s)
    sign = 1.0 if action == "reverse" else -1.0
    return sign * float(characteristic_gain) * kc * c * g


def _default_omega_range(controller: Any, plant: Any) -> tuple[float, float]:
    """Six decades around the loop's own frequencies (1/Ti, 1/Td, 1/delay, |poles|, |zeros|)."""
    kc, ti, td, _ = _controller_terms(controller)
    num, den, delay = _plant_terms(plant)
    f = [1.0 / x for x in (ti, td or None, delay or None) if x is not None and math.isfinite(x)]
    f += [abs(r) for r in np.concatenate([np.roots(num), np.roots(den)]) if abs(r) > 0]
    f = f or [1.0]
    return 1e-3 * min(f), 1e3 * max(f)


def predict_limit_cycle(S: float, J: float, controller: Any, plant: Any, *, characteristic_gain: float = 1.0,
                        derivative_filter: float | None = DERIVATIVE_FILTER,
                        omega_range: tuple[float, float] | None = None,
                        max_amplitude: float | None = None, points_per_decade: int = 40) -> Prediction:
    """Predict the limit cycle of a loop with a sticky valve by harmonic balance (module docstring).

    Parameters
    ----------
    S, J : stiction parameters, % travel (2005 convention).
    controller, plant : see :func:`loop_frequency_response`.
    characteristic_gain : slope d(flow)/d(MV) of the flow characteristic at the operating point.
    derivative_filter : ``N_d`` of the controller's derivative filter; None for the ideal ``T_d s``.
    omega_range : (lo, hi) rad/s searched; default six decades around the loop's own frequencies.
    max_amplitude : largest OP amplitude searched, % travel; default ``S/2 + 1000 max(S, J)``.
    points_per_decade : density of the scan grid in both variables.

    Returns
    -------
    Prediction
        The stable solution with the smallest amplitude, or ``found=False`` (NaN values) when none.
    """
    if not (math.isfinite(S) and S >= 0 and math.isfinite(J) and J >= 0):
        raise ValueError(f"S and J must be finite and >= 0, got S={S!r}, J={J!r}")
    if not math.isfinite(characteristic_gain) or characteristic_gain == 0:
        raise ValueError(f"characteristic_gain must be finite and nonzero, got {characteristic_gain!r}")
    none = Prediction(math.nan, math.nan, math.nan, False)
    scale = max(S, J)
    if scale == 0:
        return none  # no friction: N = 1 for every amplitude, nothing for an amplitude to balance
    w_lo, w_hi = omega_range if omega_range is not None else _default_omega_range(controller, plant)
    if not 0 < w_lo < w_hi:
        raise ValueError(f"omega_range must be 0 < lo < hi, got {(w_lo, w_hi)!r}")
    a0 = 0.5 * S
    a_hi = max_amplitude if max_amplitude is not None else a0 + 1e3 * scale
    if not a_hi > a0:
        raise ValueError(f"max_amplitude must be > S/2 = {a0!r}, got {a_hi!r}")

    def L(w):
        return loop_frequency_response(w, controller, plant, characteristic_gain=characteristic_gain,
                                       derivative_filter=derivative_filter)

    def residual(u, v):
        n = describing_function(a0 + np.exp(u), S, J)
        return np.log(-n * L(np.exp(v)))

    u_lo, u_hi = math.log(1e-6 * scale), math.log(a_hi - a0)
    v_lo, v_hi = math.log(w_lo), math.log(w_hi)
    nu = max(int(points_per_decade * (u_hi - u_lo) / math.log(10)), 10)
    nv = max(int(points_per_decade * (v_hi - v_lo) / math.log(10)), 10)
    u = np.linspace(u_lo, u_hi, nu)
    v = np.linspace(v_lo, v_hi, nv)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.log(-describing_function(a0 + np.exp(u), S, J)[:, None] * L(np.exp(v))[None, :])
    cells = _candidate_cells(r)

    def fun(x):
        z = residual(x[0], x[1])
        return [z.real, z.imag]

    found: list[tuple[float, float]] = []
    for i, k in cells:
        x0 = [0.5 * (u[i] + u[i + 1]), 0.5 * (v[k] + v[k + 1])]
        with np.errstate(all="ignore"):
            sol = optimize.root(fun, x0, method="hybr", options={"xtol": 1e-12})
        if not sol.success or not np.all(np.isfinite(sol.x)) or np.hypot(*fun(sol.x)) > 1e-8:
            continue
        if not (u_lo - 1 <= sol.x[0] <= u_hi + 1 and v_lo - 1 <= sol.x[1] <= v_hi + 1):
            continue
        if all(abs(sol.x[0] - a) > 1e-6 or abs(sol.x[1] - b) > 1e-6 for a, b in found):
            found.append((float(sol.x[0]), float(sol.x[1])))
    solutions = sorted((HarmonicBalanceSolution(a0 + math.exp(a), math.exp(b), _stable(fun, a, b))
                        for a, b in found), key=lambda s: s.amplitude)
    stable = [s for s in solutions if s.stable]
    if not stable:
        return Prediction(math.nan, math.nan, math.nan, False, tuple(solutions))
    best = stable[0]
    return Prediction(best.amplitude, best.period, best.omega, True, tuple(solutions))


def _candidate_cells(r: np.ndarray) -> list[tuple[int, int]]:
    """Grid cells where both the log-magnitude and the phase mismatch change sign (a root is likely).

    Cells touching a phase mismatch beyond +-90 deg are skipped: there the principal log may jump by 2 pi.
    """
    re, im = r.real, r.imag
    corners_re = np.stack([re[:-1, :-1], re[1:, :-1], re[:-1, 1:], re[1:, 1:]])
    corners_im = np.stack([im[:-1, :-1], im[1:, :-1], im[:-1, 1:], im[1:, 1:]])
    with np.errstate(invalid="ignore"):
        ok = np.all(np.isfinite(corners_re), axis=0) & np.all(np.abs(corners_im) < 0.5 * np.pi, axis=0)
        re_change = (corners_re.min(axis=0) <= 0) & (corners_re.max(axis=0) >= 0)
        im_change = (corners_im.min(axis=0) <= 0) & (corners_im.max(axis=0) >= 0)
    return [(int(i), int(k)) for i, k in np.argwhere(ok & re_change & im_change)]


def _stable(fun, u: float, v: float, h: float = 1e-6) -> bool:
    """Loeb's criterion: det of d(Re r, Im r)/d(u, v) > 0 (central differences)."""
    du = (np.array(fun([u + h, v])) - np.array(fun([u - h, v]))) / (2 * h)
    dv = (np.array(fun([u, v + h])) - np.array(fun([u, v - h]))) / (2 * h)
    return bool(du[0] * dv[1] - dv[0] * du[1] > 0)
