"""The tuning test's ring check: does the identified linear loop ring as regularly as the record cycles?

See :func:`ring_check`. It lives with the decision, which asks it, because it filters with the diagnosis' own
IIR filter (:func:`~valve_emulator.diagnosis.fit.linear.iir_filter`: scipy's ``lfilter``, the same bits, without
importing :mod:`scipy.signal`), which the candidates do not import.
"""

from __future__ import annotations

import numpy as np

from valve_emulator.detectors.base import oscillation
from valve_emulator.diagnosis.candidates.tuning import ARX_ORDERS, RING_SIMULATIONS, RingCheck, arx_plant
from valve_emulator.diagnosis.fit.linear import iir_filter

__all__ = ["ring_check"]


def ring_check(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None, kc: float, ti: float, dt: float,
               lag: int, orders: tuple[int, int] = ARX_ORDERS) -> RingCheck | None:
    """Does the linear loop the tuning test judged (the ARX plant of :func:`arx_plant` under the identified PI)
    ring as regularly as the data cycle? None when that loop is unstable (it does not ring, it grows).

    A linear loop under a random load rings: the load's power near the loop's resonance is amplified, and the
    ring's period wanders as the load's phase does, the more the wider the resonance. A limit cycle (a sticky
    valve's: stick, wind up, slip) repeats itself, however noisy its timing. So the loop is run as a closed loop
    on its own terms: the ARX plant, its prediction errors (white, with the variance of its residuals on the
    data) as the load, the identified PI (velocity form, its lag) on the recorded set point. Thornhill et al.'s
    regularity index of the simulated control error is compared with the data's over
    :data:`RING_SIMULATIONS` records of the data's length (a fixed random sequence, so the answer is repeatable);
    the data's cycle is beyond what the loop makes when it is at least as regular as all but a share
    :data:`RING_ALPHA` of them (a Monte Carlo test; the index and the simulated records are those of the
    oscillation summary, so the test has no threshold of its own but its level)."""
    op, pv = np.asarray(op, dtype=float), np.asarray(pv, dtype=float)
    a, b = arx_plant(op, pv, orders)
    s = max(orders)
    bq = np.r_[0.0, b]                                     # OP_{k-1} ... OP_{k-nb}
    y, u = pv - pv.mean(), op - op.mean()
    sigma = float(np.std((iir_filter(a, [1.0], y) - iir_filter(bq, [1.0], u))[s:]))   # the ARX's prediction errors
    ki = kc * dt / ti if np.isfinite(ti) else 0.0
    cn = np.array([kc + ki, -kc])                          # (1 - q⁻¹) OP = (kc (1 - q⁻¹) + ki) e
    feed = np.convolve(bq, cn)
    den = np.zeros(max(a.size + 1, feed.size + lag))
    den[:a.size + 1] += np.convolve([1.0, -1.0], a)
    den[lag:lag + feed.size] += feed
    if not np.all(np.abs(np.roots(den)) < 1.0):
        return None
    setpoint = np.zeros(y.size) if sp is None else np.asarray(sp, dtype=float) - float(sp[0])
    e_data = (np.zeros(y.size) if sp is None else np.asarray(sp, dtype=float)) - pv
    observed = oscillation(e_data).regularity
    burn = 10 * s
    drive = np.r_[np.zeros(burn), setpoint]
    forced = iir_filter(feed, den, drive)
    rng = np.random.default_rng(0)
    rings = iir_filter([1.0, -1.0], den, rng.normal(0.0, sigma, (RING_SIMULATIONS, drive.size)).T)
    sims = np.array([oscillation(setpoint - (forced + rings[:, i])[burn:]).regularity
                     for i in range(RING_SIMULATIONS)])
    sims = np.nan_to_num(sims, nan=0.0)
    p = (1.0 + np.count_nonzero(sims >= observed)) / (RING_SIMULATIONS + 1.0)
    return RingCheck(float(observed), float(sims.max()), float(p))
