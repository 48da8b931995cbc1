r"""Writing up the accepted physics: parameters, 95 % intervals, windows and the evidence sentence.

For each candidate a round of the search accepted, :func:`findings` compares the model with it against the
model without it (the round's baseline, or the sub-option without it for a pair): the improvement of the
squared residual is located in time (:func:`~valve_emulator.diagnosis.explain.locate.locate`), the cost
surface is profiled around the final value for the intervals
(:func:`~valve_emulator.diagnosis.fit.uncertainty.intervals`: with the residual's effective sample size,
over the linear part's time constants too, and on a grid stretched about the estimate while the 95 % region
reaches its edge), an estimate on an edge of the range searched
(:meth:`~valve_emulator.diagnosis.candidates.base.Candidate.bounds`) is reported as a bound ("R ≥ 400"), not
as a value, and a valve finding is scored again under a drifting-load noise model
(:mod:`~valve_emulator.diagnosis.fit.load_check`), against a linear valve on the same linear part.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from valve_emulator.diagnosis.candidates import get
from valve_emulator.diagnosis.candidates.base import Candidate, Kind
from valve_emulator.diagnosis.explain.locate import Located, locate
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.explain.search import Model, Round
from valve_emulator.diagnosis.fit.cost import relative_cost
from valve_emulator.diagnosis.fit.data import Problem
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.frame import TRAVEL, Frame
from valve_emulator.diagnosis.fit.linear import PRIOR_WIDTH, LinearStructure
from valve_emulator.diagnosis.fit.load_check import load_bic
from valve_emulator.diagnosis.fit.nominal import Nominal
from valve_emulator.diagnosis.fit.records import Surface
from valve_emulator.diagnosis.fit.scorer import Scorer
from valve_emulator.diagnosis.fit.uncertainty import (
    block_windows,
    effective_fraction,
    intervals,
    jackknifed,
    left_out,
    optimum,
    plausible,
    touches_edge,
)

__all__ = ["findings", "param_text", "parameter_intervals", "stiction_surface"]

#: Factor by which a profile grid is stretched about the estimate when the 95 % region reaches its edge, and
#: how many times at most (±40 % becomes ±80 %, then ±160 %).
_STRETCH, _STRETCHES = 2.0, 2
#: Relative distance from a declared search edge within which an estimate sits on it.
_ON_EDGE = 1e-3
#: Rows of a profile grid pushed through the chain at once for the jackknife (bounded memory).
_JACKKNIFE_CHUNK = 64


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


def stiction_surface(rounds: list[Round]):
    """ΔBIC over (S, J) from the stiction scan of the round that accepted stiction (else round 1), on the
    samples the scan scored (the fit part, or a long record's windows: :mod:`~valve_emulator.diagnosis.fit.windows`),
    the best (S, J) of that option, and whether the scan was scored through the drifting-load noise model
    (:attr:`Surface.load_model <valve_emulator.diagnosis.fit.records.Surface>`); ``None, None, False`` when no
    stiction option was scanned."""
    pick = None
    for rnd in rounds:
        for o in rnd.options:
            accepted = rnd.chosen is not None and "stiction" in rnd.chosen.added
            if o.added == ("stiction",) and o.scan is not None and (pick is None or accepted):
                pick = o
    if pick is None:
        return None, None, False
    P, sse = pick.scan.params, pick.scan.sse
    S, J = np.unique(P[:, 0]), np.unique(P[:, 1])
    cost = relative_cost(sse, pick.scan.n)
    grid = np.full((J.size, S.size), np.nan)
    iS, iJ = np.searchsorted(S, P[:, 0]), np.searchsorted(J, P[:, 1])
    for a, b, c in zip(iJ, iS, cost):
        grid[a, b] = c if np.isnan(grid[a, b]) else min(grid[a, b], c)
    best = pick.model.by_slot()["valve"].params
    return (S, J, grid), (float(best[0]), float(best[1])), pick.scan.load_model


def _interval_text(name: str, lo: float, hi: float) -> str:
    """``"S 2.1–2.6"``, or a one-sided bound (``"R ≥ 400"``) for an interval open on one side."""
    if np.isinf(hi):
        return f"{name} ≥ {lo:.4g}"
    if np.isinf(lo):
        return f"{name} ≤ {hi:.4g}"
    return f"{name} {lo:.4g}–{hi:.4g}"


def _evidence(delta_bic: float, f0: float, f1: float, ivs: dict, loc: Located, load: float | None = None) -> str:
    text = (f"against the model without it, BIC falls by {delta_bic:.0f} and the held-out fit rises from "
            f"{f0:.1f} % to {f1:.1f} %")
    if load is not None:
        change = f"falls by {load:.0f}" if load >= 0 else f"rises by {-load:.0f}"
        text += f" (under a drifting-load noise model BIC {change})"

    if ivs:
        text += "; 95 % interval " + ", ".join(_interval_text(k, a, b) for k, (a, b) in ivs.items())
    strong = [a for a in loc.alignments if a.energy_share >= 0.2 and a.lift > 1.2]
    if strong:
        text += f"; the improvement is concentrated: {strong[0].sentence()}"
    return text + "."


def _n_scale(problem: Problem, model: Model) -> float:
    """Factor turning the fit part's N into an effective sample size for the intervals: the effective fraction
    of the final model's residual on the fit part
    (:func:`~valve_emulator.diagnosis.fit.uncertainty.effective_fraction`).

    With a nominal model too: a real loop's residual is coloured by the load and by every way the model is
    only close to the plant, and treating its samples as independent made the intervals ten times too narrow.
    """
    w0, w1 = problem.train
    return effective_fraction((problem.y - model.y_hat)[w0:w1])


def _pole_variants(st: LinearStructure) -> list[tuple[LinearStructure, float]]:
    """The linear part's time constants as fitted and scaled by e^(±σ) (σ the prior's width, 25 %), each with
    its prior penalty ((ln scale)/σ)² = 1: the profile is taken over them too (:func:`_score_rows`)."""
    out = [(st, 0.0)]
    if st.taus:
        f = float(np.exp(PRIOR_WIDTH))
        out += [(replace(st, taus=tuple(t * s for t in st.taus)), 1.0) for s in (1.0 / f, f)]
    return out


def _score_rows(fitter: Fitter, model: Model, slot: str, cand: Candidate, rows: np.ndarray, n_eff: float
                ) -> Surface:
    """The profile of candidate ``cand`` in ``slot`` of ``model`` at ``rows``: the rest held as
    :meth:`~valve_emulator.diagnosis.fit.fitter.Fitter.profile` holds it (a free dead time re-chosen), and
    the linear part's time constants too (:func:`_pole_variants`, the gain re-fitted at each).

    The interval then says when the linear part is uncertain: a valve band or a lag that trades off against the
    plant's poles is not pinned by a profile that holds them. A variant's prior penalty p enters as the factor
    e^(p/N_eff) on its SSE, so that N_eff ln SSE gains exactly p.
    """
    scorer = fitter.scorer
    rest, jobs, penalties = _profile_jobs(scorer, model, slot)
    results = scorer.sse_jobs(rest, scorer.ctx(model), cand, rows, jobs, scorer.aim(model))
    return fitter.surface(cand.name, rows, _over_variants(results, penalties, n_eff))


def _profile_jobs(scorer, model: Model, slot: str) -> tuple[dict, list, np.ndarray]:
    """What a profile of the candidate in ``slot`` holds (the rest of ``model``), the linear structures and dead
    times it scores each row at (:func:`_pole_variants`), and their prior penalties."""
    rest = {k: v for k, v in model.by_slot().items() if k != slot}
    st = model.fit.structure
    delays = scorer.near(st.delay, 3) if model.delay_free else None
    variants = _pole_variants(st)
    return rest, [(v, delays) for v, _ in variants], np.array([p for _, p in variants])


def _over_variants(results: list[tuple], penalties: np.ndarray, n_eff: float) -> np.ndarray:
    """Each row's SSE at its best linear variant and dead time, a variant's SSE weighted by its prior penalty."""
    return np.min([r[0].min(axis=1) * np.exp(p / max(n_eff, 1.0)) for r, p in zip(results, penalties)], axis=0)


def _jackknifes(fitter: Fitter) -> bool:
    """Whether intervals are widened by the delete-a-block jackknife (:func:`_left_out`): with a nominal model.

    Without one the linear part is identified from the record itself, and one identified per block is free
    enough to stand in for the valve: on the package's own recordings as plant data the jackknife widened
    intervals of S that held the truth three to twenty times.
    """
    return bool(fitter.nominal.given)


def _left_out(fitter: Fitter, model: Model, slot: str, cand: Candidate, surf: Surface, n_eff: float,
              axes: tuple[int, ...]) -> np.ndarray:
    """The delete-a-block jackknife's estimates of the columns ``axes`` of ``cand`` in ``slot``
    (:func:`~valve_emulator.diagnosis.fit.uncertainty.left_out`), among the rows of the profile ``surf`` that the
    whole record allows (:func:`~valve_emulator.diagnosis.fit.uncertainty.plausible`): each scored on each of
    the fit part's blocks with the rest of ``model`` held as :func:`_score_rows` holds it, and the linear part's
    gain and taps re-fitted on the block alone at the fitted poles (the profile's pole variants moved no
    jackknifed interval of the drawn sticky loops, and cost three times the time)."""
    scorer = fitter.scorer
    rows = surf.params[plausible(surf.sse, n_eff, cand.n_params)]
    rest, jobs, _ = _profile_jobs(scorer, model, slot)
    ctx, aim, p = scorer.ctx(model), scorer.aim(model), scorer.p
    blocks = [Scorer(replace(p, train=w), scorer.nominal, scorer.library) for w in block_windows(p.train)]
    sse = np.empty((len(blocks), rows.shape[0]))
    for a in range(0, rows.shape[0], _JACKKNIFE_CHUNK):
        flows = scorer.chain(rest, ctx, cand, rows[a:a + _JACKKNIFE_CHUNK])
        for i, block in enumerate(blocks):
            sse[i, a:a + flows.shape[1]] = block.sse_flows_all(flows, jobs[:1], aim)[0][0].min(axis=1)
    return left_out(rows, sse, axes)


def _limits(cand: Candidate, ctx, surf: Surface, axis: int) -> tuple[float, float]:
    """Where a stretched grid must stop along ``axis``: 0 for a parameter the grid never takes negative (a
    band, a lag), and the candidate's declared search edges."""
    lo, hi = cand.search_range(ctx)
    floor = 0.0 if surf.params[:, axis].min() >= 0.0 else -np.inf
    return max(floor, float(lo[axis])), float(hi[axis])


def _profile(fitter: Fitter, model: Model, slot: str, cand: Candidate, best: np.ndarray, n_eff: float,
             axes: tuple[int, ...]) -> Surface:
    """The profile of candidate ``cand`` in ``slot`` around ``best``: over its profile grid and the linear
    part's time constants (:func:`_score_rows`), stretched about ``best`` by :data:`_STRETCH` (at most
    :data:`_STRETCHES` times) while the 95 % region reaches an edge of the grid along one of ``axes`` that is
    neither 0 for a positive parameter nor a declared search edge: an interval cut by the grid would claim a
    precision the data do not have."""
    ctx = fitter.scorer.ctx(model)
    surf = _score_rows(fitter, model, slot, cand, cand.profile_grid(ctx, best), n_eff)
    for _ in range(_STRETCHES):
        grow = []
        for ax in axes:
            lo, hi = _limits(cand, ctx, surf, ax)
            at_lo, at_hi = touches_edge(surf.params, surf.sse, n_eff, cand.n_params, ax)
            col = surf.params[:, ax]
            if (at_lo and col.min() > lo) or (at_hi and col.max() < hi):
                grow.append((ax, lo, hi))
        if not grow:
            return surf
        rows = surf.params.copy()
        for ax, lo, hi in grow:
            rows[:, ax] = np.clip(best[ax] + _STRETCH * (rows[:, ax] - best[ax]), lo, hi)
        surf = _score_rows(fitter, model, slot, cand, np.unique(rows, axis=0), n_eff)
    return surf


def _surface(fitter: Fitter, model: Model, act, n_eff: float, axes: tuple[int, ...]) -> Surface:
    """The cost surface an accepted candidate's intervals come from: :func:`_profile` for a chain candidate,
    :meth:`~valve_emulator.diagnosis.fit.fitter.Fitter.profile` otherwise (an output candidate, the dead time)."""
    if act.candidate.kind is not Kind.CHAIN or not axes:
        return fitter.profile(model, act.name)
    return _profile(fitter, model, act.slot, act.candidate, act.params, n_eff, axes)


def _deadband_as_stiction(fitter: Fitter, model: Model, act, n_eff: float) -> dict[str, tuple[float, float]]:
    """95 % intervals of S and J when the accepted valve is a deadband (J = 0 by construction).

    A deadband is the stiction valve without its slip, and closed-loop data often cannot tell a band with a
    slip of nearly S from one without: the stiction candidate is profiled in the valve slot around the
    deadband's S, with J from 0 to 2 S (stretched like any profile), so that both intervals say how large a
    band and a slip the data still allow.
    """
    stc = fitter.library.get("stiction") or get("stiction")
    S0, start = float(act.params[0]), float(act.params[-1])
    surf = _profile(fitter, model, act.slot, stc, np.array([S0, S0, start]), n_eff, (0, 1))
    ivs = intervals(surf.params, surf.sse, n_eff, ("S", "J"), stc.n_params, axes=(0, 1))
    if not _jackknifes(fitter):
        return ivs
    best = {"S": optimum(surf.params, surf.sse, 0), "J": optimum(surf.params, surf.sse, 1)}  # this profile's own
    return jackknifed(ivs, best, _left_out(fitter, model, act.slot, stc, surf, n_eff, (0, 1)), ("S", "J"))


def _on_edges(cand: Candidate, ctx, p: np.ndarray) -> dict[str, tuple[str, float]]:
    """The parameters whose estimate sits on a declared search edge: name → (``"≥"`` or ``"≤"``, the edge)."""
    out = {}
    for name, (lo, hi) in cand.bounds(ctx).items():
        v = float(p[cand.param_names.index(name)])
        if hi is not None and v >= hi * (1.0 - _ON_EDGE):
            out[name] = ("≥", float(hi))
        elif lo is not None and v <= lo * (1.0 + _ON_EDGE):
            out[name] = ("≤", float(lo))
    return out


def _as_bounds(ivs: dict, edges: dict[str, tuple[str, float]]) -> dict:
    """The intervals with a parameter on a search edge open on its far side: the data allow anything beyond."""
    out = dict(ivs)
    for name, (sign, edge) in edges.items():
        out[name] = (edge, np.inf) if sign == "≥" else (-np.inf, edge)
    return out


def _edge_text(edges: dict[str, tuple[str, float]]) -> str:
    """``" (R at the edge of the range searched: a bound, not a value)"``, or ``""``; the phrase before it says
    the bound itself (``R ≥ 400``, :func:`~valve_emulator.diagnosis.candidates.base.said`)."""
    if not edges:
        return ""
    return f" ({', '.join(edges)} at the edge of the range searched: a bound, not a value)"


def _described(cand: Candidate, p_user: np.ndarray, nominal_info: dict | None, units: str,
               edges: dict[str, tuple[str, float]]) -> str:
    """The finding's phrase: :meth:`~valve_emulator.diagnosis.candidates.base.Candidate.describe`, handed the
    parameters on an edge (empty where none is), then :func:`_edge_text`."""
    return cand.describe(p_user, nominal_info, units=units, edges=edges) + _edge_text(edges)


def parameter_intervals(fitter: Fitter, problem: Problem, model: Model, act, params: dict) -> tuple[dict, dict]:
    """The 95 % intervals of a candidate's parameters (``act`` in ``model``: the final one, or an option an
    answer rests on; ``params`` its JSON parameters) and the parameters on a search edge (:func:`_on_edges`), in
    the search's frame."""
    cand = act.candidate
    names = tuple(k for k, v in params.items() if isinstance(v, (int, float)) and k in cand.param_names)
    axes = tuple(cand.param_names.index(k) for k in names)
    n_eff = problem.n_fit * _n_scale(problem, model)
    surf = _surface(fitter, model, act, n_eff, axes)
    ivs = intervals(surf.params, surf.sse, n_eff, names, cand.n_params, axes=axes) if names else {}
    if cand.kind is Kind.CHAIN and names and _jackknifes(fitter):
        estimate = {k: float(act.params[ax]) for k, ax in zip(names, axes)}
        ivs = jackknifed(ivs, estimate, _left_out(fitter, model, act.slot, cand, surf, n_eff, axes), names)
    if act.name == "deadband":
        band = _deadband_as_stiction(fitter, model, act, n_eff)
        ivs["S"] = (min(ivs["S"][0], band["S"][0]), max(ivs["S"][1], band["S"][1]))
        ivs["J"] = (0.0, max(0.0, band["J"][1]))
    if cand.slot == "valve" or (axes and surf.params[:, list(axes)].min() >= 0.0):
        ivs = {k: (max(0.0, a), b) for k, (a, b) in ivs.items()}  # a band, a jump, a lag: not negative
    # The profile re-chooses a free dead time on whole samples, the estimate has the polished one: the data are
    # consistent with both, so the interval reaches the estimate.
    ivs = {k: (min(a, float(params[k])), max(b, float(params[k]))) if isinstance(params.get(k), float)
           else (a, b) for k, (a, b) in ivs.items()}
    edges = _on_edges(cand, fitter.scorer.ctx(model), act.params)
    return _as_bounds(ivs, edges), edges


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


def _load_delta_bic(scorer, without: Model, with_: Model) -> float:
    """ΔBIC of a valve finding under the drifting-load noise model
    (:mod:`~valve_emulator.diagnosis.fit.load_check`), with the model without it scored from the linear part of
    the model with it: the two differ by the valve alone, so the figure weighs the valve against a linear valve
    with a drifting load, not one plant against another. Each search model keeps its own plant otherwise, and
    two plants the search's error model rates alike can differ by tens of BIC under the drifting-load one (a
    plant at the causal bound, Δt and no dead time, against an integrator with a long dead time), which the
    valve would then be charged with."""
    at_call = replace(without, fit=replace(without.fit, structure=with_.fit.structure), delay_free=with_.delay_free)
    return load_bic(scorer, at_call)[0] - load_bic(scorer, with_)[0]


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
            ivs, edges = parameter_intervals(fitter, problem, model, act, params)
            dbic = without.bic - chosen.model.bic
            load = None
            if cand.slot == "valve":   # with or without a nominal model: the strength of either reads it
                load = _load_delta_bic(scorer, without, chosen.model)
            nominal_info = {"theta": nominal.delay} if nominal.given else None
            params, ivs, units, p_user = _in_op_units(cand, act.params, params, ivs, frame)
            if not frame.identity:
                edges = {k: (sign, frame.convert(cand.dims, {k: v})[k]) for k, (sign, v) in edges.items()}
            out.append(Finding(physics=name, parameters=params, windows=loc.windows,
                               evidence=_evidence(dbic, without.heldout, chosen.model.heldout, ivs, loc, load),
                               description=_described(cand, p_user, nominal_info, units, edges),
                               intervals=ivs,
                               delta_bic=dbic, fit_without=without.heldout, fit_with=chosen.model.heldout,
                               load_delta_bic=load, edges=edges))
    return tuple(out)


