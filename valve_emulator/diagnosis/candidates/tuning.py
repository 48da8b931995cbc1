r"""Candidate ``tuning``: the loop cycles through its own controller — aggressive tuning with a linear valve.

An aggressively tuned loop rings: disturbances near the frequency where the loop's phase lag approaches
180° are amplified, and routine data show a cycle even though the valve is fine. Replaying OP through the
plant then explains PV well *without* any valve nonlinearity, so no ``chain`` or ``output`` candidate
improves the model: the cause lies in the feedback path, which the diagnosis cuts (it replays the recorded
OP). This candidate therefore adds nothing to the replayed model (``loop`` kind, not searched) and is
judged afterwards on the fitted plant by :meth:`Tuning.assess`:

1. **Controller** from the data: a PI in velocity form, least squares on

   .. math::  \Delta\mathrm{OP}_k = k_p\,\Delta e_k + k_i\,e_k + c, \qquad e = \mathrm{SP} - \mathrm{PV}

   (without a set point ``e = −PV`` and ``c`` absorbs the constant), so :math:`K_c = k_p`,
   :math:`T_i = k_p\,\Delta t / k_i`. Its :math:`R^2` says whether OP is the PI's output at all (a cascade
   slave or a manual-biased loop is not); below :data:`MIN_R2` tuning is not judged.
2. **Loop**: :math:`L = C(e^{j\omega\Delta t})\,G(j\omega)\,e^{-j\omega\Delta t/2}` with the discrete PI,
   the fitted plant (gain, time constants, dead time, integrator) and the zero-order hold's half-sample
   lag. The maximum sensitivity :math:`M_s = \max_\omega |1/(1+L)|` measures how much the loop amplifies
   disturbances; Åström & Hägglund (*Advanced PID Control*, ISA 2006, §4) recommend :math:`M_s` between 1.2
   and 2, so a loop with :math:`M_s \ge` :data:`MS_AGGRESSIVE` (= 2) — or a gain margin below 1, an
   unstable linear loop — is aggressively tuned.
3. **The cycle is the loop's**: its period must match the one the loop amplifies most,
   :math:`2\pi/\omega_{peak}`, within :data:`PERIOD_TOLERANCE`.

Parameters reported: ``kc``, ``ti``, ``ms`` and the predicted ``period``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainContext, LoopCandidate, register

__all__ = ["Tuning", "TuningAssessment", "MS_AGGRESSIVE", "PERIOD_TOLERANCE", "MIN_R2"]

#: Maximum sensitivity at and above which a loop is aggressively tuned (Åström & Hägglund 2006).
MS_AGGRESSIVE = 2.0
#: Observed and predicted periods must agree within this fraction.
PERIOD_TOLERANCE = 0.3
#: Least R² of the PI fit for the controller to count as identified.
MIN_R2 = 0.5


@dataclass(frozen=True)
class TuningAssessment:
    """What :meth:`Tuning.assess` found.

    Attributes
    ----------
    judged : the controller was identified (R² ≥ :data:`MIN_R2`) and the loop gain has the sign of negative
        feedback, so the other numbers mean something.
    aggressive : the loop is aggressively tuned and its cycle is the loop's own (all three tests).
    kc, ti : identified PI (OP % per PV unit, s); ``ti`` is inf for a P-only controller.
    r2 : fit of the PI model.
    ms, gain_margin : maximum sensitivity and gain margin of the identified loop.
    period : period the loop amplifies most (s); ``observed`` the cycle's period in the data (NaN: none).
    reason : one sentence.
    """

    judged: bool
    aggressive: bool
    kc: float = float("nan")
    ti: float = float("nan")
    r2: float = float("nan")
    ms: float = float("nan")
    gain_margin: float = float("nan")
    period: float = float("nan")
    observed: float = float("nan")
    reason: str = ""

    def parameters(self) -> dict:
        return {"kc": float(f"{self.kc:.4g}"), "ti": float(f"{self.ti:.4g}"), "ms": round(self.ms, 2),
                "period": round(self.period, 1)}


def identify_pi(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None, dt: float) -> tuple[float, float, float]:
    """``(Kc, Ti, R²)`` of the velocity-form PI fitted by least squares (see the module docstring)."""
    e = (np.asarray(sp, dtype=float) - pv) if sp is not None else -np.asarray(pv, dtype=float)
    d_op = np.diff(op)
    X = np.column_stack([np.diff(e), e[1:], np.ones(d_op.size)])
    coef, *_ = np.linalg.lstsq(X, d_op, rcond=None)
    res = d_op - X @ coef
    tot = float(np.sum((d_op - d_op.mean()) ** 2))
    r2 = 1.0 - float(res @ res) / tot if tot > 0 else 0.0
    kp, ki = float(coef[0]), float(coef[1])
    ti = kp * dt / ki if ki != 0.0 and kp * ki > 0 else float("inf")
    return kp, ti, r2


def loop_response(kc: float, ti: float, dt: float, gain: float, taus, delay: float, integrating: bool,
                  omega: np.ndarray) -> np.ndarray:
    """Loop transfer ``L(jω)`` of the discrete PI and the fitted plant (see the module docstring)."""
    z1 = np.exp(-1j * omega * dt)
    ki = kc * dt / ti if np.isfinite(ti) else 0.0
    c = (kc * (1.0 - z1) + ki) / (1.0 - z1)
    g = gain * np.exp(-1j * omega * (delay + dt / 2.0))
    for tau in taus:
        g = g / (1.0 + 1j * omega * tau)
    if integrating:
        g = g / (1j * omega)
    return c * g


class Tuning(LoopCandidate):
    name: ClassVar[str] = "tuning"
    slot: ClassVar[str] = "loop"
    param_names: ClassVar[tuple[str, ...]] = ("kc", "ti")
    n_params: ClassVar[int] = 2

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return np.zeros((0, 2))  # identified by least squares, not searched

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        return best[None, :]


    def assess(self, *, op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None, dt: float, gain: float,
               taus=(), delay: float = 0.0, integrating: bool = False,
               observed_period: float = float("nan")) -> TuningAssessment:
        """Judge the loop (see the module docstring). ``gain`` is the fitted plant's, PV units per % (per
        second when ``integrating``); ``observed_period`` the data's cycle (s), NaN when it has none."""
        kc, ti, r2 = identify_pi(np.asarray(op, dtype=float), np.asarray(pv, dtype=float), sp, dt)
        if r2 < MIN_R2:
            return TuningAssessment(False, False, kc, ti, r2, observed=observed_period,
                                    reason=f"OP is not a PI controller's output of SP − PV (R² {r2:.2f} < "
                                           f"{MIN_R2}), so the tuning cannot be judged")
        if kc * gain <= 0.0:
            return TuningAssessment(False, False, kc, ti, r2, observed=observed_period,
                                    reason="the identified controller and plant do not form a negative "
                                           "feedback loop, so the tuning cannot be judged")
        n = op.shape[0]
        omega = np.geomspace(2.0 * np.pi / (n * dt), np.pi / dt, 2000)
        L = loop_response(kc, ti, dt, gain, tuple(taus), delay, integrating, omega)
        sens = 1.0 / np.abs(1.0 + L)
        ms, i = float(sens.max()), int(np.argmax(sens))
        phase = np.unwrap(np.angle(L))
        cross = np.flatnonzero((phase[:-1] > -np.pi) & (phase[1:] <= -np.pi))
        gm = 1.0 / float(np.abs(L[cross[0] + 1])) if cross.size else float("inf")
        w = omega[cross[0] + 1] if gm < 1.0 and cross.size else omega[i]
        period = 2.0 * np.pi / w
        rings = ms >= MS_AGGRESSIVE or gm < 1.0
        matches = np.isfinite(observed_period) and abs(observed_period / period - 1.0) <= PERIOD_TOLERANCE
        what = (f"PI Kc = {kc:.3g} %/unit, Ti = {ti:.3g} s (R² {r2:.2f}); with the fitted plant the loop has "
                f"Ms = {ms:.2f}, gain margin {gm:.2f} and amplifies most at a period of {period:.3g} s")
        if not np.isfinite(observed_period):
            tail = "; the data show no regular cycle"
        else:
            tail = f"; the data cycle with a period of {observed_period:.3g} s"
        return TuningAssessment(True, bool(rings and matches), kc, ti, r2, ms, gm, period, observed_period,
                                what + tail)

    def parameters(self, p: np.ndarray) -> dict:
        return {"kc": float(p[0]), "ti": float(p[1])}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %") -> str:
        return f"aggressive tuning: PI Kc ≈ {p[0]:.3g}, Ti ≈ {p[1]:.3g} s"


register(Tuning())
