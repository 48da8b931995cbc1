r"""Candidate ``tuning``: the loop cycles through its own controller — aggressive tuning with a linear valve.

An aggressively tuned loop rings: disturbances near the frequency where the loop's phase lag approaches
180° are amplified, and routine data show a cycle even though the valve is fine. Replaying OP through the
plant then explains PV well *without* any valve nonlinearity, so no ``chain`` or ``output`` candidate
improves the model: the cause lies in the feedback path, which the diagnosis cuts (it replays the recorded
OP). This candidate therefore adds nothing to the replayed model (``loop`` kind, not searched) and is
judged afterwards on the fitted plant by :meth:`Tuning.assess`:

1. **Controller** from the data: a PI in velocity form, least squares on

   .. math::  \Delta\mathrm{OP}_k = k_p\,\Delta e_k + k_i\,e_k + c, \qquad e_k = \mathrm{SP}_k - \mathrm{PV}_{k-d}

   (without a set point ``e = −PV`` and ``c`` absorbs the constant), so :math:`K_c = k_p`,
   :math:`T_i = k_p\,\Delta t / k_i`. The lag ``d`` is 0 (OP at sample k from PV at k) or 1 (from PV at
   k − 1, as a DCS acts on the PV it sampled one cycle before); the one with the better :math:`R^2` is kept
   and reported. The :math:`R^2` says whether OP is the PI's output at all (a cascade slave or a
   manual-biased loop is not); below :data:`MIN_R2` tuning is not judged.
2. **Loop**: the plant as the closed loop shows it, a high-order ARX model
   :math:`A(q)\,\mathrm{PV}_k = B(q)\,\mathrm{OP}_{k-1} + \varepsilon_k` (orders :data:`ARX_ORDERS`, at
   least one sample of delay), fitted by least squares — the direct prediction-error method, consistent on
   closed-loop data when the noise model (here :math:`1/A`) can describe the load (Ljung, *System
   Identification*, 2nd ed., §13.4), where the replay of OP the search fits is biased by the controller's
   answer to the load. Then :math:`L = C(e^{j\omega\Delta t})\,z^{-d}\,B/A` with the discrete PI and its lag
   ``d``. The maximum sensitivity :math:`M_s = \max_\omega |1/(1+L)|` measures
   how much the loop amplifies disturbances; Åström & Hägglund (*Advanced PID Control*, ISA 2006, §4)
   recommend :math:`M_s` between 1.2 and 2, so a loop with :math:`M_s \ge` :data:`MS_AGGRESSIVE` (= 2) — or a
   gain margin below :data:`GM_AGGRESSIVE` (= 2) — is aggressively tuned. The two bounds agree: a loop
   with :math:`M_s < 2` has a gain margin of at least :math:`M_s/(M_s - 1) > 2` (the Nyquist curve stays
   outside the circle of radius :math:`1/M_s` around −1), and Åström & Hägglund's recommended gain margins
   are 2–5, so a gain margin under 2 is aggressive whatever :math:`M_s` the grid resolved. Above
   :data:`MS_EDGE` the ARX has put the loop at the edge of instability to explain a cycle that never decays,
   which a periodic load explains as well (a single frequency cannot tell them apart), so the loop is judged
   with the fitted plant's own loop instead (:func:`loop_response`: the discrete PI, the plant,
   ``(d + ½)Δt``), whose Ms is always reported beside (``plant_ms``).
3. **The cycle is the loop's**: its period must match the one the loop amplifies most,
   :math:`2\pi/\omega_{peak}`, within :data:`PERIOD_TOLERANCE` — the record's most regular cycle, or, when
   that is another cycle (a slow load's) or the record cycles irregularly, the control error's own cycle once
   everything slower than :data:`SLOWER` times the loop's period is removed (:func:`own_cycle`; isolating one
   oscillation of several by filtering, as Thornhill, Huang & Zhang, *J. Process Control* 13 (2003) 91–100,
   do). An aggressive loop under a random load rings at its own period without ringing regularly, and a slow
   periodic load can be the record's most regular cycle while the loop rings underneath.
4. **The ring is as irregular as a ring is** (:func:`~valve_emulator.diagnosis.assess.ring.ring_check`, asked
   by the plant-data decision for an aggressive loop whose ring is the
   record's own regular cycle, judged with the ARX loop): the identified loop is run as a closed loop on its
   own terms (the ARX plant, its prediction errors as the load, the PI on the recorded set point) over
   :data:`RING_SIMULATIONS` records, and when the data's control error cycles more regularly (Thornhill et
   al.'s index) than all but :data:`RING_ALPHA` of them, the cycle is one the linear loop does not make — a
   limit cycle (a sticky valve's) or an oscillation from outside — and the plant-data decision does not name
   tuning (an accepted periodic load at that period, else ``cannot tell`` naming both;
   :mod:`~valve_emulator.diagnosis.assess.decision`). The fitted
   plant cannot tell: the search places its dead time where the loop's phase crossover matches the cycle,
   so period and gain at the cycle are consistent by construction; how regularly the cycle repeats is not.

Parameters reported: ``kc``, ``ti``, ``ms`` and the predicted ``period``.

**With a nominal model** the controller and the plant are given, so the margins need no identification:
:func:`nominal_margins` computes them from the continuous loop
:math:`L(s) = K_c\,(1 + 1/(T_i s) + T_d s)\,G(s)\,e^{-s(\theta + (d + 1/2)\Delta t)}`: the nominal plant
with its dead time θ, the ideal PI(D), and what sampling adds, half a sample of hold and ``d`` samples of
controller delay. This is the convention of the independent simulator's truth
(:func:`valve_emulator.benchmark.independent.loop_margins`, 1.5 Δt for a PI one sample late).
:mod:`valve_emulator.diagnosis.assess.margins` uses it on the with-model path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from valve_emulator.detectors.base import oscillation
from valve_emulator.diagnosis.candidates.base import ChainContext, LoopCandidate, register

__all__ = ["Tuning", "TuningAssessment", "Margins", "MS_AGGRESSIVE", "GM_AGGRESSIVE", "PERIOD_TOLERANCE",
           "MIN_R2", "MS_EDGE", "ARX_ORDERS", "SLOWER", "arx_plant", "identify_pi", "loop_response", "margins",
           "nominal_margins", "own_cycle", "RING_SIMULATIONS", "RING_ALPHA", "RingCheck", "rings_at_the_cycle"]

#: Maximum sensitivity at and above which a loop is aggressively tuned (Åström & Hägglund 2006).
MS_AGGRESSIVE = 2.0
#: Gain margin below which a loop is aggressively tuned (Åström & Hägglund recommend 2–5; see the module docstring).
GM_AGGRESSIVE = 2.0
#: Ms above which the ARX loop sits at the edge of instability: a periodic load explains the cycle as well.
MS_EDGE = 10.0
#: Orders (na, nb) of the ARX model of PV on OP that the tuning check judges the loop with.
ARX_ORDERS = (10, 20)
#: Observed and predicted periods must agree within this fraction.
PERIOD_TOLERANCE = 0.3
#: Least R² of the PI fit for the controller to count as identified.
MIN_R2 = 0.5
#: Records simulated through the identified linear loop to ask whether it rings as regularly as the data cycle
#: (:func:`~valve_emulator.diagnosis.assess.ring.ring_check`) ...
RING_SIMULATIONS = 99
#: ... and the test's level: the data's cycle is beyond the ring when at most this share of the simulated
#: records (the data counted as one of them) cycles as regularly (1 %: none of the 99).
RING_ALPHA = 0.01
#: :func:`own_cycle` removes what is slower than this many times the loop's own period (a moving mean that long
#: passes the loop's period whole: its first zero is at that period's double).
SLOWER = 2.0


@dataclass(frozen=True)
class Margins:
    """Robustness of a loop: maximum sensitivity ``ms``, gain margin ``gain_margin`` (inf: the phase never
    reaches −180°), phase margin ``phase_margin`` (degrees; inf: the loop gain never falls through 1) and the
    ``period`` (s) the loop amplifies most, 2π over the frequency of the sensitivity's peak."""

    ms: float
    gain_margin: float
    phase_margin: float
    period: float

    @property
    def aggressive(self) -> bool:
        """Ms ≥ :data:`MS_AGGRESSIVE` or a gain margin below :data:`GM_AGGRESSIVE` (see the module docstring)."""
        return self.ms >= MS_AGGRESSIVE or self.gain_margin < GM_AGGRESSIVE

    def text(self) -> str:
        return (f"Ms {self.ms:.2f}, gain margin {self.gain_margin:.2f}, phase margin {self.phase_margin:.0f}°; it "
                f"amplifies most at a period of {self.period:.3g} s")


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
    lag : samples between the PV the controller acts on and its OP (0 or 1; see :func:`identify_pi`).
    ms, gain_margin, phase_margin : maximum sensitivity, gain margin and phase margin (°) of the loop with the
        ARX plant (see the module docstring); ``plant_ms`` the maximum sensitivity with the fitted plant.
    period : period the loop amplifies most (s); ``observed`` the cycle's period in the data (NaN: none).
    reason : one sentence.
    load_alike : the ARX loop sat at the edge of instability (Ms > :data:`MS_EDGE`), so a periodic load explains
        the cycle as well and the loop was judged with the fitted plant instead.
    ring : for an aggressive loop whose ring is the record's own regular cycle (judged with the ARX loop), whether
        that loop rings as regularly as the data cycle
        (:func:`~valve_emulator.diagnosis.assess.ring.ring_check`, filled in by the plant-data decision); None
        otherwise.
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
    lag: int = 0
    phase_margin: float = float("nan")
    plant_ms: float = float("nan")
    load_alike: bool = False
    ring: RingCheck | None = None

    def parameters(self) -> dict:
        return {"kc": float(f"{self.kc:.4g}"), "ti": float(f"{self.ti:.4g}"), "ms": round(self.ms, 2),
                "period": round(self.period, 1)}


def _same(observed: float, period: float) -> bool:
    """An observed period (NaN: none) within :data:`PERIOD_TOLERANCE` of the loop's."""
    return bool(np.isfinite(observed) and abs(observed / period - 1.0) <= PERIOD_TOLERANCE)


def _pi_fit(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None, lag: int,
            dt: float) -> tuple[float, float, float]:
    """``(Kc, Ti, R²)`` of ΔOP_k on Δe_k, e_k and a constant with ``e_k = SP_k − PV_{k−lag}`` (the set point
    of the cycle, the PV sampled ``lag`` cycles before), over the samples both lags share."""
    n = pv.size
    pv_seen = pv[1 - lag:n - lag]                 # PV_{k−lag} for k = 1 … n−1
    e = (sp[1:] if sp is not None else 0.0) - pv_seen
    y = np.diff(op[1:])                           # ΔOP_k for k = 2 … n−1
    X = np.column_stack([np.diff(e), e[1:], np.ones(y.size)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ coef
    tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(res @ res) / tot if tot > 0 else 0.0
    kp, ki = float(coef[0]), float(coef[1])
    ti = kp * dt / ki if ki != 0.0 and kp * ki > 0 else float("inf")
    return kp, ti, r2


def identify_pi(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None,
                dt: float) -> tuple[float, float, float, int]:
    """``(Kc, Ti, R², lag)`` of the velocity-form PI fitted by least squares (see the module docstring): OP
    from the PV of the same sample (lag 0) or of one sample before (lag 1), whichever fits better."""
    op, pv = np.asarray(op, dtype=float), np.asarray(pv, dtype=float)
    sp = None if sp is None else np.asarray(sp, dtype=float)
    fits = [(*_pi_fit(op, pv, sp, lag, dt), lag) for lag in (0, 1)]
    return max(fits, key=lambda f: f[2])


def own_cycle(pv: np.ndarray, sp: np.ndarray | None, dt: float, period: float) -> float:
    """The period (s) the control error SP − PV (−PV without a set point) cycles at once what is slower than
    :data:`SLOWER` × ``period`` is removed (its centred moving mean over that span subtracted): the mean period
    of Thornhill et al.'s zero-crossing test, regular or not (NaN when too few crossings)."""
    e = (np.asarray(sp, dtype=float) if sp is not None else 0.0) - np.asarray(pv, dtype=float)
    n = int(min(max(round(SLOWER * period / dt), 2), e.size))
    slow = np.convolve(np.pad(e, (n // 2, n - 1 - n // 2), mode="edge"), np.ones(n) / n, mode="valid")
    return float(oscillation(e - slow).period) * dt


def arx_plant(op: np.ndarray, pv: np.ndarray, orders: tuple[int, int] = ARX_ORDERS):
    """``(a, b)`` of the ARX model of the module docstring: ``a = [1, a₁ … a_na]`` (PV_k + Σ a_i PV_{k−i}) and
    ``b = [b₁ … b_nb]`` on OP_{k−1} … OP_{k−nb}, both signals centred."""
    na, nb = orders
    y, u = pv - pv.mean(), op - op.mean()
    s = max(na, nb)
    X = np.column_stack([y[s - i:y.size - i] for i in range(1, na + 1)] + [u[s - j:u.size - j]
                                                                          for j in range(1, nb + 1)])
    coef, *_ = np.linalg.lstsq(X, y[s:], rcond=None)
    return np.r_[1.0, -coef[:na]], coef[na:]


@dataclass(frozen=True)
class RingCheck:
    """Whether the identified linear loop rings as regularly as the data cycle
    (:func:`~valve_emulator.diagnosis.assess.ring.ring_check`).

    Attributes
    ----------
    regularity : the control error's regularity index r in the data (Thornhill et al. 2003).
    simulated : the largest r among the records simulated through the loop.
    p : the share of the simulated records, the data counted as one of them, that cycle at least as regularly.
    beyond : ``p`` ≤ :data:`RING_ALPHA`: the data cycle more regularly than the loop rings.
    """

    regularity: float
    simulated: float
    p: float

    @property
    def beyond(self) -> bool:
        return self.p <= RING_ALPHA

    def text(self) -> str:
        return (f"the control error cycles with a regularity r = {self.regularity:.3g}, while the identified loop, "
                f"driven by its own prediction errors, rings at most at r = {self.simulated:.3g} in "
                f"{RING_SIMULATIONS} simulated records of the same length")


def rings_at_the_cycle(t: TuningAssessment) -> bool:
    """Whether the ring check applies: the loop judged aggressive with the ARX loop (not at its edge), its ring
    the record's own regular cycle (not one found under a slower cycle)."""
    return t.aggressive and not t.load_alike and _same(t.observed, t.period)


def _arx_loop(kc: float, ti: float, dt: float, lag: int, a: np.ndarray, b: np.ndarray,
              omega: np.ndarray) -> np.ndarray:
    """``L(e^{jωΔt})`` of the discrete PI, its lag and the ARX plant ``B/A``."""
    z1 = np.exp(-1j * omega * dt)
    ki = kc * dt / ti if np.isfinite(ti) else 0.0
    c = (kc * (1.0 - z1) + ki) / (1.0 - z1) * z1 ** lag
    return c * z1 * np.polyval(b[::-1], z1) / np.polyval(a[::-1], z1)


def loop_response(kc: float, ti: float, dt: float, gain: float, taus, delay: float, integrating: bool,
                  omega: np.ndarray, lag: int = 0) -> np.ndarray:
    """Loop transfer ``L(jω)`` of the discrete PI and the fitted plant (see the module docstring)."""
    z1 = np.exp(-1j * omega * dt)
    ki = kc * dt / ti if np.isfinite(ti) else 0.0
    c = (kc * (1.0 - z1) + ki) / (1.0 - z1)
    g = gain * np.exp(-1j * omega * (delay + (lag + 0.5) * dt))
    for tau in taus:
        g = g / (1.0 + 1j * omega * tau)
    if integrating:
        g = g / (1j * omega)
    return c * g


def loop_phase(L: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """The unwrapped phase (rad) of the loop response ``L`` on the ascending grid ``omega``, on the branch its
    low frequencies fix: a loop of negative feedback whose magnitude falls as ω⁻ⁿ at the grid's first points
    (n integrators: the PI's, an integrating plant's) has a phase near −n·90° there. ``np.angle`` alone
    cannot tell −180° − ε from 180° − ε: a PI on an integrating plant starts at about −180°, and a start on the
    wrong branch put every phase a turn too high (a phase margin of 384°, a gain margin read at −540°)."""
    phase = np.unwrap(np.angle(L))
    slope = np.log(np.abs(L[1]) / np.abs(L[0])) / np.log(omega[1] / omega[0])
    integrators = max(0, int(round(-slope)))
    turns = np.round((phase[0] + integrators * np.pi / 2.0) / (2.0 * np.pi))
    return phase - 2.0 * np.pi * turns


def margins(L: np.ndarray, omega: np.ndarray) -> Margins:
    """:class:`Margins` of the loop response ``L`` on the ascending frequency grid ``omega`` (rad/s): the
    gain margin at the first crossing of −180° by the unwrapped phase (:func:`loop_phase`), the phase margin at
    the first fall of ``|L|`` through 1, each interpolated between the grid points around it."""
    sens = 1.0 / np.abs(1.0 + L)
    peak = int(np.argmax(sens))
    phase = loop_phase(L, omega)
    mag = np.abs(L)
    cross = np.flatnonzero((phase[:-1] > -np.pi) & (phase[1:] <= -np.pi))
    gm = float("inf")
    if cross.size:
        i = cross[0]
        f = (phase[i] + np.pi) / (phase[i] - phase[i + 1])
        gm = 1.0 / float(np.exp(np.log(mag[i]) + f * (np.log(mag[i + 1]) - np.log(mag[i]))))
    unit = np.flatnonzero((mag[:-1] >= 1.0) & (mag[1:] < 1.0))
    pm = float("inf")
    if unit.size:
        i = unit[0]
        f = np.log(mag[i]) / (np.log(mag[i]) - np.log(mag[i + 1]))
        pm = float(np.degrees(np.pi + phase[i] + f * (phase[i + 1] - phase[i])))
    return Margins(float(sens[peak]), gm, pm, float(2.0 * np.pi / omega[peak]))


def nominal_margins(num, den, delay: float, kc: float, ti: float | None, td: float, *, action: str,
                    extra_delay: float) -> Margins | None:
    """:class:`Margins` of the continuous loop of a nominal plant ``num/den·e^{−delay·s}`` and a PI(D)
    ``kc(1 + 1/(ti·s) + td·s)`` with ``extra_delay`` seconds of sampling delay (see the module docstring).
    ``action`` is ``reverse`` (OP rises when PV falls below SP) or ``direct``. None when the controller's
    action and the plant's gain do not make negative feedback (the margins mean nothing then)."""
    num, den = np.atleast_1d(np.asarray(num, float)), np.atleast_1d(np.asarray(den, float))
    low = den[np.flatnonzero(den)[-1]]                         # the lowest nonzero power decides the sign
    sign = 1.0 if action == "reverse" else -1.0
    if sign * num[np.flatnonzero(num)[-1]] * low <= 0.0:
        return None
    scale = max(delay + extra_delay, *(1.0 / abs(r) for r in np.roots(den) if abs(r) > 0), 1e-3)
    omega = np.geomspace(1e-5, 1e2, 100_000) / scale
    s = 1j * omega
    pid = kc * (1.0 + (1.0 / (ti * s) if ti else 0.0) + td * s)
    L = sign * pid * np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * (delay + extra_delay))
    return margins(L, omega)


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
        kc, ti, r2, lag = identify_pi(np.asarray(op, dtype=float), np.asarray(pv, dtype=float), sp, dt)
        late = " one sample late" if lag else ""
        if r2 < MIN_R2:
            return TuningAssessment(False, False, kc, ti, r2, observed=observed_period, lag=lag,
                                    reason=f"OP is not a PI controller's output of SP − PV, at the same sample or "
                                           f"one sample late (R² {r2:.2f} < {MIN_R2}), so the tuning cannot be "
                                           "judged")
        if kc * gain <= 0.0:
            return TuningAssessment(False, False, kc, ti, r2, observed=observed_period, lag=lag,
                                    reason="the identified controller and plant do not form a negative "
                                           "feedback loop, so the tuning cannot be judged")
        op, pv = np.asarray(op, dtype=float), np.asarray(pv, dtype=float)
        n = op.shape[0]
        omega = np.geomspace(2.0 * np.pi / (n * dt), 0.999 * np.pi / dt, 4000)
        fitted = margins(loop_response(kc, ti, dt, gain, tuple(taus), delay, integrating, omega, lag), omega)
        m = margins(_arx_loop(kc, ti, dt, lag, *arx_plant(op, pv), omega), omega)
        what = (f"PI Kc = {kc:.3g} %/unit, Ti = {ti:.3g} s (R² {r2:.2f}, acting on PV{late or ' at once'}); "
                f"with the plant the closed loop shows (ARX) the loop has {m.text()} (with the fitted plant: Ms "
                f"{fitted.ms:.2f})")
        if not np.isfinite(observed_period):
            tail = "; the data show no regular cycle"
        else:
            tail = f"; the data cycle with a period of {observed_period:.3g} s"
        load_alike = m.ms > MS_EDGE
        if load_alike:
            tail += (f"; at Ms > {MS_EDGE:g} the ARX loop sits at the edge of instability, which a periodic load "
                     "explains as well, so the loop is judged with the fitted plant")
            m = fitted
        matches = _same(observed_period, m.period)
        if not matches:
            own = own_cycle(pv, sp, dt, m.period)
            matches = _same(own, m.period)
            if matches:
                tail += (f"; once what is slower than {SLOWER:g} times that period is removed, the control error "
                         f"cycles at {own:.3g} s")
        aggressive = m.aggressive and matches
        return TuningAssessment(True, bool(aggressive), kc, ti, r2, m.ms, m.gain_margin, m.period,
                                observed_period, what + tail, lag, m.phase_margin, fitted.ms, load_alike)

    def parameters(self, p: np.ndarray) -> dict:
        return {"kc": float(p[0]), "ti": float(p[1])}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"aggressive tuning: PI Kc ≈ {p[0]:.3g}, Ti ≈ {p[1]:.3g} s"


register(Tuning())
