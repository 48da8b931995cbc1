r"""``diagnose(recording, nominal)``: replay, locate, search the candidate library, report.

1. **Replay** the nominal model on the recorded OP (:mod:`~valve_emulator.diagnosis.fit.nominal`); its
   held-out free-run fit is ``fit_before``. Without a nominal model the linear part is identified from the
   data first and *that* is the nominal model.
2. **Locate** the residual in time and operating conditions (:mod:`~valve_emulator.diagnosis.explain.locate`).
3. **Search** (:mod:`~valve_emulator.diagnosis.explain.search`): add the most significant candidate physics,
   round after round, the linear part re-fitted around each.
4. **Report** each accepted piece with its parameters, 95 % intervals from the cost surface, where it
   reduces the residual (windows) and why it was accepted (evidence); ``fit_after`` is the final model's
   held-out fit.

Validation: with a nominal model the last 30 % of the record is held out (``validation="split"``); without
one — plant data, where the plant is unknown and the evidence may sit anywhere in the record — the search
fits the whole record and cross-validates on two blocks (``"twofold"``, see
:mod:`~valve_emulator.diagnosis.fit.crossval`). Either can be asked for explicitly.

Which cost: PV itself, or a high-pass prefiltered PV for an integrating plant (see
:func:`~valve_emulator.diagnosis.fit.linear.highpass`): the prefilter makes an integrator's cost smooth in the
valve parameters, but would only throw away a self-regulating plant's slow response. With a nominal model
its plant decides; without one the search runs on PV (its pole set spans both families) and, if the result
integrates, once more prefiltered, whose result is kept.
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np

from valve_emulator.config import LoopConfig
from valve_emulator.diagnosis.candidates import get, registry
from valve_emulator.diagnosis.fit.chain import run_chain
from valve_emulator.diagnosis.fit.data import HELD_OUT, Problem, fit_percent, prefilter_for, prepare
from valve_emulator.diagnosis.fit.load_check import load_delta_bic
from valve_emulator.diagnosis.explain.locate import Located, condition_masks, locate
from valve_emulator.diagnosis.fit.nominal import Nominal, identify, nominal_from_config, replay_plant
from valve_emulator.diagnosis.report.explanation import Diagnosis, Finding, RankRow, Traces
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT, Model, Round, Search
from valve_emulator.diagnosis.fit.uncertainty import intervals
from valve_emulator.recordings.recording import Recording

__all__ = ["diagnose", "RULE", "RULE_TWOFOLD"]

RULE = (f"An addition counts when BIC (N ln σ̂² + k ln N on the fit part) falls by at least {DELTA_BIC:g} and the "
        f"free-run fit on the held-out last 30 % rises by at least {DELTA_FIT:g} points, against the current "
        "model and against each of its own sub-options; the lowest-BIC option that counts is added.")
#: The rule without a nominal model (``validation="twofold"``).
RULE_TWOFOLD = (f"An addition counts when BIC with an AR(1) error model (N ln σ̂²_w + (k + 1) ln N on the whole "
                f"record after the burn-in, σ̂_w the prewhitened residual) falls by at least {DELTA_BIC:g} and the "
                f"free-run fit cross-validated on two blocks (first and last 30 %) rises by at least "
                f"{DELTA_FIT:g} points, against the current model and against each of its own sub-options; the "
                "lowest-BIC option that counts is added.")


def _replay_nominal(problem: Problem, nominal: Nominal, search: Search) -> np.ndarray:
    """Nominal chain + exact nominal plant on the recorded OP; only the operating point is fitted."""
    flow = search.chain({}, search.ctx(None))[:, 0]
    y0 = replay_plant(nominal, flow, problem.dt)
    T = problem.T
    cols = [np.ones(T)] + ([np.arange(T) / T] if nominal.structure.integrating else [])
    X = np.column_stack(cols)
    w0, w1 = problem.train
    coef, *_ = np.linalg.lstsq(X[w0:w1], (problem.pv - y0)[w0:w1], rcond=None)
    return y0 + X @ coef


def _gain(num: Sequence[float], den: Sequence[float]) -> float:
    den = np.trim_zeros(np.asarray(den, dtype=float), "b")  # an integrator's s drops out: gain per second
    return float(num[-1] / den[-1])


def _linear_table(nominal: Nominal, model: Model, problem: Problem) -> dict:
    st, fit = model.fit.structure, model.fit
    k = fit.gain * problem.y_scale
    unit = " (per s)" if st.integrating else ""
    nom_k = f"{_gain(nominal.num, nominal.den):.4g}" if nominal.given else "—"
    taus = lambda s: ", ".join(f"{t:.4g}" for t in s.taus) or "—"  # noqa: E731
    return {f"gain, PV per % flow{unit}": (nom_k, f"{k:.4g}"),
            "time constants (s)": (taus(nominal.structure) if nominal.given else "—", taus(st)),
            "dead time (s)": (f"{nominal.delay:.4g}" if nominal.given else "—", f"{st.delay:.4g}"),
            "integrating": ("yes" if nominal.structure.integrating else "no",) * 2}


def _param_text(model: Model, added: tuple[str, ...]) -> str:
    parts = []
    for a in model.active:
        if a.name in added:
            parts.append(", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in a.candidate.parameters(a.params).items() if v is not None))
    return "; ".join(parts)


def _surface(rounds: list[Round], n: int):
    """ΔBIC over (S, J) from the stiction scan of the round that accepted stiction (else round 1)."""
    pick = None
    for rnd in rounds:
        for o in rnd.options:
            if o.added == ("stiction",) and o.scan is not None:
                if pick is None or (rnd.chosen is not None and "stiction" in rnd.chosen.added):
                    pick = o
    if pick is None:
        return None, None
    P, sse = pick.scan.params, pick.scan.sse
    S, J = np.unique(P[:, 0]), np.unique(P[:, 1])
    cost = n * np.log(np.maximum(sse, 1e-300) / max(sse.min(), 1e-300))
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


def _slip_interval(search: Search, model: Model, act, n: float) -> tuple[float, float]:
    """95 % interval of the slip jump J when the accepted valve is a deadband (J = 0 by construction).

    The stiction candidate is scored on S around the deadband's S times J from 0 to S, the rest of the model
    held; the J extent of the region inside the χ²₂ bound says how large a slip the data still allow.
    """
    stc = search.library.get("stiction") or get("stiction")
    S0, start = float(act.params[0]), float(act.params[-1])
    hS = max(0.01, search.p.op_span / 160.0)
    S = S0 + hS * np.arange(-4, 5)
    S = S[S > 0]
    J = np.linspace(0.0, max(S0, 1e-3), 25)
    rows = np.array([(a, b, start) for a in S for b in J])
    rest = {k: v for k, v in model.by_slot().items() if k != "valve"}
    search.use(model)
    sse, _ = search._sse_grid(rest, search.ctx(model), stc, rows, model.fit.structure, None)
    return intervals(rows, sse[:, 0], n, ("J",), 2, axes=(1,))["J"]


def _findings(search: Search, problem: Problem, model: Model, rounds: list[Round], masks, horizon,
              nominal: Nominal) -> tuple[Finding, ...]:
    out = []
    final = {a.name: a for a in model.active}
    search.use(model)
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
            surf = search.profile(model, name)
            names = tuple(k for k, v in params.items() if isinstance(v, (int, float)) and k in cand.param_names)
            axes = tuple(cand.param_names.index(k) for k in names)
            n_eff = surf.n * _n_scale(problem, model)
            ivs = intervals(surf.params, surf.sse, n_eff, names, cand.n_params, axes=axes) if names else {}
            if name == "deadband":
                ivs["J"] = (0.0, max(0.0, _slip_interval(search, model, act, n_eff)[1]))
            if cand.slot == "valve":  # a band and a jump are not negative
                ivs = {k: (max(0.0, a), b) for k, (a, b) in ivs.items()}
            # The profile re-chooses a free dead time on whole samples, the estimate has the polished one: the
            # data are consistent with both, so the interval reaches the estimate.
            ivs = {k: (min(a, float(params[k])), max(b, float(params[k]))) if isinstance(params.get(k), float)
                   else (a, b) for k, (a, b) in ivs.items()}
            dbic = without.bic - chosen.model.bic
            load = None
            if cand.slot == "valve" and problem.validation == "twofold":
                load = load_delta_bic(search, without, chosen.model)
            nominal_info = {"theta": nominal.delay} if nominal.given else None
            out.append(Finding(name, params, loc.windows, _evidence(dbic, without.heldout, chosen.model.heldout,
                                                                    ivs, loc, load),
                               cand.describe(act.params, nominal_info), ivs, dbic, without.heldout,
                               chosen.model.heldout, load))
    return tuple(out)


def _run(recording: Recording, nom: Nominal | None, prefilter: float | None, lib: dict, say, validation: str):
    """Prepare, (identify,) search: one pass in one cost domain."""
    problem = prepare(recording, nominal_delay=nom.delay if nom else None,
                      settle_time=nom.settle_time if nom else 0.0, prefilter=prefilter, validation=validation)
    if nom is None:
        say("identifying the linear part from the data (FOPDT or IPDT)")
        nom = identify(problem)
    search = Search(problem, nom, lib, progress=say)
    model, rounds = search.run()
    return search.p, nom, search, model, rounds  # the search may have lengthened the burn-in


def diagnose(recording: Recording, nominal: LoopConfig | None = None, *,
             candidates: Sequence[str] | None = None,
             progress: Callable[[str], None] | None = None, validation: str | None = None) -> Diagnosis:
    """Diagnose what the nominal model leaves out (see the module docstring).

    Parameters
    ----------
    recording : ``t``, ``op``, ``pv`` are used (``sp`` and ``mv`` may be absent).
    nominal : the loop the user believes in; None identifies a linear model (FOPDT or IPDT) from the data.
    candidates : names from the candidate registry (default: all); ``dead_time`` needs a nominal model.
    progress : called with a short message at each stage (the CLI prints them on stderr).
    validation : ``"split"`` or ``"twofold"`` (default: split with a nominal model, two-fold without).

    Raises
    ------
    RecordingError
        Too few samples, constant OP or PV, non-uniform sampling (naming the file and line).
    ValueError
        A nominal plant the linear part cannot represent; an unknown candidate name.
    """
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    lib = registry() if candidates is None else {n: get(n) for n in candidates}
    validation = validation or ("split" if nominal is not None else "twofold")
    dt = recording.dt if len(recording) >= 2 else 1.0
    nom = nominal_from_config(nominal, dt) if nominal is not None else None
    if nom is None:
        lib.pop("dead_time", None)  # without a nominal model the dead time is simply identified
        problem, nom, search, model, rounds = _run(recording, None, None, lib, say, validation)
        st = model.fit.structure
        if st.integrating:
            say("the plant integrates: searching again on prefiltered PV")
            lam = prefilter_for(st.delay + sum(st.taus), dt)
            problem, nom, search, model, rounds = _run(recording, None, lam, lib, say, validation)
    else:
        st = nom.structure
        lam = prefilter_for(st.delay + sum(st.taus), dt) if st.integrating else None
        problem, nom, search, model, rounds = _run(recording, nom, lam, lib, say, validation)
    base = rounds[0].baseline if rounds else model
    test_start = problem.test[0] if validation == "split" else int(round((1.0 - HELD_OUT) * problem.T))
    if nom.given:
        pv_before = _replay_nominal(problem, nom, search)
        fit_before = fit_percent(problem.pv[test_start:], pv_before[test_start:])
    else:
        pv_before = problem.to_pv(base.y_hat)
        fit_before = base.heldout
    st = model.fit.structure
    horizon = max(st.delay + 2.0 * sum(st.taus), 10.0 * problem.dt)
    w = max(3, int(round(horizon / problem.dt / 2)))
    masks = condition_masks(problem.op, w=w, horizon=max(2, int(round(horizon / problem.dt))))
    located = locate(problem.t, problem.op, (problem.pv - pv_before) ** 2, dt=problem.dt,
                     response_time=horizon, masks=masks)
    say("estimating parameter intervals")
    findings = _findings(search, problem, model, rounds, masks, horizon, nom)
    ranking = tuple(RankRow(i + 1, o.label, _param_text(o.model, o.added), rnd.baseline.bic - o.model.bic,
                            o.model.heldout, o is rnd.chosen)
                    for i, rnd in enumerate(rounds) for o in rnd.options)
    ctx = search.ctx(model)
    valve_only = {k: v for k, v in model.by_slot().items() if k in ("actuator", "valve")}
    mv = run_chain(problem.op, valve_only, ctx.__class__(**{**ctx.__dict__, "characteristic": ("linear", 50.0)}),
                   nominal_valve=(nom.S, nom.J))[:, 0]
    surface, surface_best = _surface(rounds, problem.n_fit)
    traces = Traces(problem.t, problem.op, problem.pv, pv_before, problem.to_pv(base.y_hat),
                    problem.to_pv(model.y_hat), mv, model.flow, test_start, surface, surface_best)
    plant = {"gain": model.fit.gain * problem.y_scale, "taus": tuple(st.taus), "delay": st.delay,
             "integrating": st.integrating, "validation": problem.validation}
    return Diagnosis(problem.source, nom.given, fit_before, base.heldout, model.heldout, findings, located,
                     _linear_table(nom, model, problem), ranking, traces,
                     RULE if validation == "split" else RULE_TWOFOLD, time.perf_counter() - start, plant)
