r"""Writing up the accepted physics: parameters, 95 % intervals, windows and the evidence sentence.

For each candidate a round of the search accepted, :func:`findings` compares the model with it against the
model without it (the round's baseline, or the sub-option without it for a pair): the improvement of the
squared residual is located in time (:func:`~valve_emulator.diagnosis.explain.locate.locate`), the cost
surface is profiled around the final value for the intervals
(:func:`~valve_emulator.diagnosis.fit.uncertainty.intervals`, with an effective sample size when the residual
is autocorrelated), and on plant data a valve finding is scored again under a drifting-load noise model
(:mod:`~valve_emulator.diagnosis.fit.load_check`).
"""

from __future__ import annotations

import numpy as np

from valve_emulator.diagnosis.candidates import get
from valve_emulator.diagnosis.candidates.stiction import scan_steps
from valve_emulator.diagnosis.explain.locate import Located, locate
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.explain.search import Model, Round
from valve_emulator.diagnosis.fit.cost import relative_cost
from valve_emulator.diagnosis.fit.data import Problem
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.frame import TRAVEL, Frame
from valve_emulator.diagnosis.fit.load_check import load_delta_bic
from valve_emulator.diagnosis.fit.nominal import Nominal
from valve_emulator.diagnosis.fit.scorer import Scorer
from valve_emulator.diagnosis.fit.uncertainty import intervals

__all__ = ["findings", "param_text", "stiction_surface"]


def param_text(model: Model, added: tuple[str, ...], frame: Frame | None = None) -> str:
    """The parameters of the candidates ``added`` to ``model``, in OP's units when ``frame`` maps them."""
    parts = []
    for a in model.active:
        if a.name in added:
            params = a.candidate.parameters(a.params)
            if frame is not None and not frame.identity:
                params = frame.convert(a.candidate.dims, params)
            parts.append(", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in params.items() if v is not None))
    return "; ".join(parts)


def stiction_surface(rounds: list[Round], n: int):
    """ΔBIC over (S, J) from the stiction scan of the round that accepted stiction (else round 1)."""
    pick = None
    for rnd in rounds:
        for o in rnd.options:
            accepted = rnd.chosen is not None and "stiction" in rnd.chosen.added
            if o.added == ("stiction",) and o.scan is not None and (pick is None or accepted):
                pick = o
    if pick is None:
        return None, None
    P, sse = pick.scan.params, pick.scan.sse
    S, J = np.unique(P[:, 0]), np.unique(P[:, 1])
    cost = relative_cost(sse, n)
    grid = np.full((J.size, S.size), np.nan)
    iS, iJ = np.searchsorted(S, P[:, 0]), np.searchsorted(J, P[:, 1])
    for a, b, c in zip(iJ, iS, cost):
        grid[a, b] = c if np.isnan(grid[a, b]) else min(grid[a, b], c)
    best = pick.model.by_slot()["valve"].params
    return (S, J, grid), (float(best[0]), float(best[1]))


def _evidence(delta_bic: float, f0: float, f1: float, ivs: dict, loc: Located, load: float | None = None) -> str:
    text = (f"against the model without it, BIC falls by {delta_bic:.0f} and the held-out fit rises from "
            f"{f0:.1f} % to {f1:.1f} %")
    if load is not None:
        change = f"falls by {load:.0f}" if load >= 0 else f"rises by {-load:.0f}"
        text += f" (under a drifting-load noise model BIC {change})"

    if ivs:
        text += "; 95 % interval " + ", ".join(f"{k} {a:.4g}–{b:.4g}" for k, (a, b) in ivs.items())
    strong = [a for a in loc.alignments if a.energy_share >= 0.2 and a.lift > 1.2]
    if strong:
        text += f"; the improvement is concentrated: {strong[0].sentence()}"
    return text + "."


def _n_scale(problem: Problem, model: Model) -> float:
    """Factor turning the fit part's N into an effective sample size for the intervals.

    With white errors (a nominal model, ``"split"``) it is 1. Without one the final residual is autocorrelated
    and each sample carries less information: for AR(1) errors with lag-1 correlation ρ the variance of an
    average grows by (1 + ρ)/(1 − ρ) (Bartlett), so N is scaled by (1 − ρ)/(1 + ρ) (at most 1, at least 1/N).
    """
    if problem.validation == "split":
        return 1.0
    w0, w1 = problem.train
    r = (problem.y - model.y_hat)[w0:w1]
    den = float(r[:-1] @ r[:-1])
    rho = float(np.clip(r[1:] @ r[:-1] / den, 0.0, 0.999)) if den > 0 else 0.0
    return max((1.0 - rho) / (1.0 + rho), 1.0 / max(r.size, 1))


def _slip_interval(scorer: Scorer, model: Model, act, n: float) -> tuple[float, float]:
    """95 % interval of the slip jump J when the accepted valve is a deadband (J = 0 by construction).

    The stiction candidate is scored on S around the deadband's S times J from 0 to S, the rest of the model
    held; the J extent of the region inside the χ²₂ bound says how large a slip the data still allow.
    """
    stc = scorer.library.get("stiction") or get("stiction")
    S0, start = float(act.params[0]), float(act.params[-1])
    hS = scan_steps(scorer.p.op_span)[0]
    S = S0 + hS * np.arange(-4, 5)
    S = S[S > 0]
    J = np.linspace(0.0, max(S0, 1e-3), 25)
    rows = np.array([(a, b, start) for a in S for b in J])
    rest = {k: v for k, v in model.by_slot().items() if k != "valve"}
    sse, _ = scorer.sse_grid(rest, scorer.ctx(model), stc, rows, model.fit.structure, None, scorer.aim(model))
    return intervals(rows, sse[:, 0], n, ("J",), 2, axes=(1,))["J"]


def _in_op_units(cand, act_params: np.ndarray, params: dict, ivs: dict, frame: Frame) -> tuple:
    """Parameters, intervals and the description from the search's frame in OP's units (4 significant digits)."""
    p_user = np.array(act_params, dtype=float)
    for i, name in enumerate(cand.param_names):
        if cand.dims.get(name) == "op":
            p_user[i] = frame.op_delta(p_user[i])
        elif cand.dims.get(name) == "op_level":  # a level at the frame's stops (0, 100) is no level: NaN
            v = p_user[i]
            p_user[i] = frame.stop_level(v) if 0.0 < v < 100.0 else np.nan
    units = " %" if frame.units == TRAVEL else f" {frame.units}"
    if not frame.identity:
        params = {k: float(f"{v:.4g}") if isinstance(v, float) else v
                  for k, v in frame.convert(cand.dims, params).items()}
        ivs = frame.convert(cand.dims, ivs)
    return params, ivs, units, p_user


def findings(fitter: Fitter, problem: Problem, model: Model, rounds: list[Round], masks, horizon,
             nominal: Nominal, frame: Frame | None = None) -> tuple[Finding, ...]:
    """One :class:`Finding` per candidate accepted in ``rounds``, in the order accepted (see the module
    docstring); ``model`` is the final model, ``masks`` and ``horizon`` those the residual was located with,
    ``frame`` the map of OP into the search's frame (parameters are reported in OP's units; default: % travel)."""
    frame = frame or Frame()
    scorer = fitter.scorer
    out = []
    final = {a.name: a for a in model.active}
    for rnd in rounds:
        if rnd.chosen is None:
            continue
        chosen = rnd.chosen
        for name in chosen.added:
            rest = set(chosen.added) - {name}
            without = rnd.baseline if not rest else next(o.model for o in rnd.options if set(o.added) == rest)
            r0, r1 = problem.y - without.y_hat, problem.y - chosen.model.y_hat
            loc = locate(problem.t, problem.op, r0 ** 2 - r1 ** 2, dt=problem.dt, response_time=horizon,
                         masks=masks)
            act = final[name]
            cand = act.candidate
            params = cand.parameters(act.params)
            surf = fitter.profile(model, name)
            names = tuple(k for k, v in params.items() if isinstance(v, (int, float)) and k in cand.param_names)
            axes = tuple(cand.param_names.index(k) for k in names)
            n_eff = surf.n * _n_scale(problem, model)
            ivs = intervals(surf.params, surf.sse, n_eff, names, cand.n_params, axes=axes) if names else {}
            if name == "deadband":
                ivs["J"] = (0.0, max(0.0, _slip_interval(scorer, model, act, n_eff)[1]))
            if cand.slot == "valve":  # a band and a jump are not negative
                ivs = {k: (max(0.0, a), b) for k, (a, b) in ivs.items()}
            # The profile re-chooses a free dead time on whole samples, the estimate has the polished one: the
            # data are consistent with both, so the interval reaches the estimate.
            ivs = {k: (min(a, float(params[k])), max(b, float(params[k]))) if isinstance(params.get(k), float)
                   else (a, b) for k, (a, b) in ivs.items()}
            dbic = without.bic - chosen.model.bic
            load = None
            if cand.slot == "valve" and problem.validation == "twofold":
                load = load_delta_bic(scorer, without, chosen.model)
            nominal_info = {"theta": nominal.delay} if nominal.given else None
            params, ivs, units, p_user = _in_op_units(cand, act.params, params, ivs, frame)
            out.append(Finding(physics=name, parameters=params, windows=loc.windows,
                               evidence=_evidence(dbic, without.heldout, chosen.model.heldout, ivs, loc, load),
                               description=cand.describe(p_user, nominal_info, units=units), intervals=ivs,
                               delta_bic=dbic, fit_without=without.heldout, fit_with=chosen.model.heldout,
                               load_delta_bic=load))
    return tuple(out)


