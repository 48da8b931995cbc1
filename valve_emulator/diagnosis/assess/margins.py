r"""Tuning named as tuning when a nominal model is given: the loop's margins, and physics that only imitates a ring.

A PI tuned too aggressively for its loop rings: the closed loop amplifies the load near the frequency where its
phase lag approaches 180°, and the recording cycles at that period with a perfectly healthy valve. With a
nominal model nothing needs identifying: the model holds the controller (Kc, Ti) and the plant, so
:func:`judge_nominal` computes the nominal loop's margins
(:func:`~valve_emulator.diagnosis.candidates.tuning.nominal_margins`: the continuous loop with the plant's dead
time and ``(d + ½)·Δt`` for sampling, half a sample of hold and the controller's delay ``d``, which is read
from the data: :func:`~valve_emulator.diagnosis.candidates.tuning.identify_pi` keeps 0 or 1 sample, whichever
explains ΔOP better). The loop is **aggressive** when Ms ≥ 2 or its gain margin is below 2 (Åström &
Hägglund; see :mod:`~valve_emulator.diagnosis.candidates.tuning`), and the tuning is **the cause** when the
recording's dominant period (the adequacy check's oscillation detector, regular or not: a loop ringing on a
random load rings irregularly, and here the margins are known, not guessed from the cycle) is the period the
nominal loop amplifies most, within the tuning test's tolerance.

**Physics that only imitates the ring.** The search fits the model as a replay of the recorded OP (an output
error). In a closed loop OP is the controller's answer to the load, so OP and the load are correlated, and
more strongly the more the loop rings: a longer dead time, an actuator lag or even a sticky valve can then
cancel part of the load's effect and buy held-out free-run fit that the nominal plant, handed the *true* load,
would not need (the bias of open-loop identification on closed-loop data; Ljung, *System Identification*,
2nd ed., §13.4). The one-step-ahead prediction error with a noise model is free of that bias (the direct
prediction-error method is consistent on closed-loop data when the noise model can describe the
disturbance, Ljung §13.4; Forssell & Ljung, *Automatica* 35 (1999) 1215–1241). So, without reading any label,
the findings of an aggressive, ringing loop must also improve the **one-step prediction** of PV:
:func:`one_step_gain` whitens the residual of the nominal replay and of the final model each with its own
AR(:data:`AR_ORDER`) noise model, fitted on the fit part, and compares them by the search's own rule —
BIC falls by at least :data:`~valve_emulator.diagnosis.explain.search.DELTA_BIC` on the fit part and the
held-out one-step fit rises by at least :data:`~valve_emulator.diagnosis.explain.search.DELTA_FIT` points.
Findings that do not are dropped as candidates and the search is run again without them
(:func:`explain_with_tuning`), so the fit, the fitted model and the twin hold only physics the nominal loop
does not already explain; ``tuning`` is then added as a finding with the margins.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from valve_emulator.config import LoopConfig
from valve_emulator.diagnosis.assess.adequacy import adequacy
from valve_emulator.diagnosis.candidates import registry
from valve_emulator.diagnosis.candidates.tuning import (
    MIN_R2,
    PERIOD_TOLERANCE,
    Margins,
    identify_pi,
    nominal_margins,
)
from valve_emulator.diagnosis.explain.pipeline import explain
from valve_emulator.diagnosis.explain.result import Explanation, Finding
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT
from valve_emulator.recordings.recording import Recording

__all__ = ["NominalTuning", "OneStep", "judge_nominal", "one_step_gain", "explain_with_tuning", "AR_ORDER"]

#: Order of the AR noise model that whitens a replay's residual for the one-step prediction.
AR_ORDER = 10


@dataclass(frozen=True)
class NominalTuning:
    """The nominal loop's tuning, judged on a recording.

    Attributes
    ----------
    kc, ti : the nominal PI (``ti`` inf for P only).
    lag : samples of controller delay read from the data (0 or 1), ``r2`` the fit of the PI that read it.
    margins : of the nominal continuous loop with ``(lag + ½)·dt`` of sampling delay; None when the nominal
        controller and plant do not make negative feedback.
    observed : the recording's dominant period (s; the adequacy check's, regular or not), NaN when it has none.
    """

    kc: float
    ti: float
    lag: int
    r2: float
    margins: Margins | None
    observed: float

    @property
    def rings(self) -> bool:
        """The recording cycles at the period the nominal loop amplifies most."""
        return (self.margins is not None and np.isfinite(self.observed)
                and abs(self.observed / self.margins.period - 1.0) <= PERIOD_TOLERANCE)

    @property
    def cause(self) -> bool:
        """Aggressive tuning is the cause of the cycle: OP is the PI's output, the loop is aggressive and rings."""
        return self.r2 >= MIN_R2 and self.margins is not None and self.margins.aggressive and self.rings

    def finding(self, dt: float, t_span: tuple[float, float], dropped: str) -> Finding:
        """The ``tuning`` finding; ``dropped`` says which findings the one-step test removed ("" if none)."""
        m = self.margins
        late = "one sample late" if self.lag else "at once"
        description = (f"aggressive tuning: with the nominal PI (Kc {self.kc:.3g}, Ti {self.ti:.3g} s) the loop has "
                       f"{m.text()}, and the record cycles at {self.observed:.3g} s")
        evidence = (f"nominal continuous loop with {(self.lag + 0.5) * dt:.3g} s of sampling delay (half a sample "
                    f"of hold, the controller acting on PV {late}: R² {self.r2:.2f}); Ms ≥ 2 or a gain margin "
                    f"below 2 is aggressive (Åström & Hägglund), and the record's cycle ({self.observed:.3g} s) is "
                    f"the loop's own ({m.period:.3g} s){dropped}")
        return Finding(physics="tuning", windows=(t_span,), evidence=evidence, description=description,
                       parameters={"kc": _sig(self.kc), "ti": _sig(self.ti), "ms": round(m.ms, 3),
                                   "gain_margin": round(m.gain_margin, 3), "phase_margin": round(m.phase_margin, 2),
                                   "period": round(m.period, 2), "observed_period": round(self.observed, 2),
                                   "controller_lag": self.lag})


def _sig(x: float) -> float:
    return float(f"{x:.4g}")


def judge_nominal(rec: Recording, cfg: LoopConfig) -> NominalTuning | None:
    """The nominal loop's tuning on ``rec`` (see the module docstring); None when the model has no controller."""
    c = cfg.controller
    if c is None:
        return None
    sp = rec.sp if rec.has_sp else None
    *_, r2, lag = identify_pi(rec.op, rec.pv, sp, rec.dt)
    ti = float(c.ti) if c.ti else float("inf")
    m = nominal_margins(cfg.plant.num, cfg.plant.den, cfg.plant.delay, c.kc, c.ti, c.td, action=c.action,
                        extra_delay=(lag + 0.5) * rec.dt)
    facts = adequacy(rec).facts
    observed = float(facts.get("period", np.nan))   # the dominant period, regular or not: a load-driven ring is
    #                                                  irregular, and the margins, not the cycle, say it rings
    return NominalTuning(kc=float(c.kc), ti=ti, lag=int(lag), r2=float(r2), margins=m, observed=observed)


@dataclass(frozen=True)
class OneStep:
    """The final model against the nominal replay, by one-step-ahead prediction (see the module docstring):
    ``delta_bic`` on the fit part (positive: the final model predicts better), one-step fits (%) on the held-out
    part ``fit_nominal`` and ``fit_final``."""

    delta_bic: float
    fit_nominal: float
    fit_final: float

    @property
    def buys(self) -> bool:
        return self.delta_bic >= DELTA_BIC and self.fit_final - self.fit_nominal >= DELTA_FIT


def _whitened(v: np.ndarray, split: int, order: int) -> np.ndarray:
    """One-step prediction errors of ``v`` (from sample ``order`` on) by an AR(``order``) model fitted on
    ``v[:split]``."""
    v = v - v[:split].mean()
    X = np.column_stack([v[order - j - 1:v.size - j - 1] for j in range(order)])
    coef, *_ = np.linalg.lstsq(X[:split - order], v[order:split], rcond=None)
    return v[order:] - X @ coef


def one_step_gain(d: Explanation, order: int = AR_ORDER) -> OneStep:
    """Compare the final model with the nominal replay by one-step prediction of PV (see the module docstring)."""
    tr = d.traces
    split = tr.test_start
    e0 = _whitened(tr.pv - tr.pv_before, split, order)
    e1 = _whitened(tr.pv - tr.pv_after, split, order)
    n = split - order
    k = sum(len(f.parameters) for f in d.findings) + len(d.moved)
    delta_bic = n * np.log(np.mean(e0[:n] ** 2) / np.mean(e1[:n] ** 2)) - k * np.log(n)
    y = tr.pv[split:]
    dev = np.linalg.norm(y - y.mean())
    fit = lambda e: float(100.0 * (1.0 - np.linalg.norm(e[n:]) / dev)) if dev > 0 else float("nan")  # noqa: E731
    return OneStep(float(delta_bic), fit(e0), fit(e1))


def explain_with_tuning(rec: Recording, cfg: LoopConfig, *, candidates: Sequence[str] | None = None,
                        validation: str | None = None,
                        progress: Callable[[str], None] | None = None) -> Explanation:
    """:func:`~valve_emulator.diagnosis.explain.pipeline.explain` against ``cfg``, then, when the nominal loop's
    tuning is the cause of the recording's cycle, without the findings that only imitate it and with a
    ``tuning`` finding (see the module docstring)."""
    d = explain(rec, cfg, candidates=candidates, validation=validation, progress=progress)
    judged = judge_nominal(rec, cfg)
    if judged is None or not judged.cause:
        return d
    say = progress or (lambda msg: None)
    names = list(registry()) if candidates is None else list(candidates)
    dropped: list[str] = []
    notes: list[str] = []
    while d.findings:
        test = one_step_gain(d)
        if test.buys:
            break
        gone = [f.physics for f in d.findings]
        notes.append(f"{', '.join(gone)} (one-step ΔBIC {test.delta_bic:.0f}, held-out one-step fit "
                     f"{test.fit_nominal:.1f} % → {test.fit_final:.1f} %)")
        dropped += gone
        say(f"the nominal loop is aggressively tuned and rings: searching again without {', '.join(gone)}")
        d = explain(rec, cfg, candidates=[n for n in names if n not in dropped], validation=validation,
                    progress=progress)
    why = ("; dropped as imitations of the ring, for they do not improve the one-step prediction of PV under a "
           "noise model: " + "; then ".join(notes)) if notes else ""
    span = (float(rec.t[0]), float(rec.t[-1]))
    return replace(d, findings=d.findings + (judged.finding(rec.dt, span, why),))
