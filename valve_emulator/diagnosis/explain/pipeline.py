r"""``explain(recording, nominal)``: replay, locate, search the candidate library, report.

1. **Replay** the nominal model on the recorded OP (:mod:`~valve_emulator.diagnosis.fit.nominal`); its
   held-out free-run fit is ``fit_before``. Without a nominal model the linear part is identified from the
   data first and *that* is the nominal model, under the closed loop's constraints
   (:mod:`~valve_emulator.diagnosis.fit.closed_loop`: causal, the gain's sign from the controller's action,
   no pole faster than a sample, the plant's family when declared), so it cannot be the controller's inverse;
   the explanation says which constraints were used (``identification``).
2. **Locate** the residual in time and operating conditions (:mod:`~valve_emulator.diagnosis.explain.locate`).
3. **Search** (:mod:`~valve_emulator.diagnosis.explain.search`): add the most significant candidate physics,
   round after round, the linear part re-fitted around each; then, with a nominal model, hold its linear part
   where the data do not demand a move (:mod:`~valve_emulator.diagnosis.explain.prior`).
4. **Report** each accepted piece with its parameters, 95 % intervals from the cost surface, where it
   reduces the residual (windows) and why it was accepted (evidence; :mod:`~valve_emulator.diagnosis.explain.
   findings`); ``fit_after`` is the final model's held-out fit, and the final model is kept
   (:class:`~valve_emulator.diagnosis.fit.predict.FittedLoop`).

Validation: with a nominal model the last 30 % of the record is held out (``validation="split"``); without
one — plant data, where the plant is unknown and the evidence may sit anywhere in the record — the search
fits the whole record and cross-validates on two blocks (``"twofold"``, see
:mod:`~valve_emulator.diagnosis.fit.crossval`). Either can be asked for explicitly.

Which cost: PV itself, or a high-pass prefiltered PV for an integrating plant (see
:func:`~valve_emulator.diagnosis.fit.linear.highpass`): the prefilter makes an integrator's cost smooth in the
valve parameters, but would only throw away a self-regulating plant's slow response. With a nominal model
its plant decides; without one the search runs on PV (its pole set spans both families) and, if the result
integrates, once more prefiltered, whose result is kept. If the result is then self-regulating and the
controller's law was read exactly, the loop is searched once more on prefiltered PV with the plant held
integrating, kept when it predicts held-out PV better through the prefilter and explains PV better under a
drifting-load noise model (:func:`_integrating_or_not`): on PV a wandering load hides an integrator.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from valve_emulator.config import LoopConfig
from valve_emulator.diagnosis._threads import one_blas_thread
from valve_emulator.diagnosis.candidates import get, registry
from valve_emulator.diagnosis.explain.findings import findings, param_text, parameter_intervals, stiction_surface
from valve_emulator.diagnosis.explain.locate import condition_masks, locate
from valve_emulator.diagnosis.explain.onset import (
    acting_part,
    delay_cap,
    far_beyond,
    post_onset_split,
    suspect_onset,
)
from valve_emulator.diagnosis.explain.prior import dead_time_move, nominal_gain, settle
from valve_emulator.diagnosis.explain.result import Explanation, LinearMove, RankRow, Traces, ValveAlternative
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT, Model, Round, Search
from valve_emulator.diagnosis.fit.chain import run_chain
from valve_emulator.diagnosis.fit.closed_loop import SETPOINT_LEVEL, Declared, identification, setpoint_delay
from valve_emulator.diagnosis.fit.crossval import cross_validated_fit, with_cv
from valve_emulator.diagnosis.fit.data import (
    HELD_OUT,
    WIDEN,
    Problem,
    delay_at_end,
    fit_percent,
    held_out_start,
    prefilter_for,
    prepare,
    widens,
    with_burn_in,
)
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.frame import TRAVEL, UNKNOWN_UNITS, Frame
from valve_emulator.diagnosis.fit.load_check import (
    Memory,
    family_delta_bic,
    input_delta_bic,
    load_delta_bic,
    remembered,
)
from valve_emulator.diagnosis.fit.nominal import Nominal, identify, nominal_from_config, replay_plant
from valve_emulator.diagnosis.fit.predict import FittedLoop
from valve_emulator.diagnosis.fit.scorer import Scorer, library_burn_in
from valve_emulator.physics.signal_chain import DEFAULT_RANGEABILITY
from valve_emulator.recordings.recording import Recording

__all__ = ["explain", "RULE", "RULE_TWOFOLD"]

#: The most BIC (under the drifting-load noise model) the integrating plant's linear part may lose against the
#: self-regulating one's when the search held integrating is kept (:func:`_integrating_or_not`). Measured on the
#: independent simulator (2026-11-26, plant data): sticky level loops held integrating lost at most 72 there; the
#: healthy flow loop under a sine load that the held search took as a sticky level loop lost 2705.
HELD_LINEAR_LOSS = 20.0 * DELTA_BIC

RULE = (f"An addition counts when BIC (N ln σ̂² + k ln N on the fit part) falls by at least {DELTA_BIC:g} and the "
        f"free-run fit on the held-out last {100 * HELD_OUT:g} % rises by at least {DELTA_FIT:g} points, against the "
        "current model and against each of its own sub-options; the lowest-BIC option that counts is added.")
#: The rule without a nominal model (``validation="twofold"``).
RULE_TWOFOLD = (f"An addition counts when BIC with an AR(1) error model (N ln σ̂²_w + (k + 1) ln N on the whole "
                f"record after the burn-in, σ̂_w the prewhitened residual) falls by at least {DELTA_BIC:g} and the "
                f"free-run fit cross-validated on two blocks (first and last {100 * HELD_OUT:g} %) rises by at least "
                f"{DELTA_FIT:g} points, against the current model and against each of its own sub-options; the "
                "lowest-BIC option that counts is added.")


def _replay_nominal(problem: Problem, nominal: Nominal, scorer: Scorer) -> np.ndarray:
    """Nominal chain + exact nominal plant on the recorded OP; only the operating point is fitted."""
    flow = scorer.chain({}, scorer.ctx(None))[:, 0]
    y0 = replay_plant(nominal, flow, problem.dt)
    T = problem.T
    cols = [np.ones(T)] + ([np.arange(T) / T] if nominal.structure.integrating else [])
    X = np.column_stack(cols)
    w0, w1 = problem.train
    coef, *_ = np.linalg.lstsq(X[w0:w1], (problem.pv - y0)[w0:w1], rcond=None)
    return y0 + X @ coef


def _linear_table(nominal: Nominal, model: Model, problem: Problem, frame: Frame, delay_is_bound: bool) -> dict:
    """The linear part, nominal against identified (``delay_is_bound``: the dead time is written "≥")."""
    st, fit = model.fit.structure, model.fit
    k = fit.gain * problem.y_scale * frame.gain
    # Per % of flow in % travel; per unit of OP otherwise (the frame's gain carries the map).
    per = "% flow" if frame.units == TRAVEL else ("OP unit" if frame.units == UNKNOWN_UNITS else frame.units)
    nom_k = f"{nominal_gain(nominal.num, nominal.den):.4g}" if nominal.given else "—"
    taus = lambda s: ", ".join(f"{t:.4g}" for t in s.taus) or "—"  # noqa: E731
    yes_no = lambda flag: "yes" if flag else "no"  # noqa: E731
    return {f"gain, PV per {per}" + (" per s" if st.integrating else ""): (nom_k, f"{k:.4g}"),
            "time constants (s)": (taus(nominal.structure) if nominal.given else "—", taus(st)),
            "dead time (s)": (f"{nominal.delay:.4g}" if nominal.given else "—",
                              f"≥ {st.delay:.4g}" if delay_is_bound else f"{st.delay:.4g}"),
            "integrating": (yes_no(nominal.structure.integrating) if nominal.given else "—", yes_no(st.integrating))}


@dataclass(frozen=True, eq=False)
class Searched:
    """One search in one cost domain: the problem as scored (burn-in lengthened for the candidates), the
    nominal model (identified when none was given), the fitter, the final model, the rounds, the tests of
    the nominal linear part and the dead-time cap its grid was cut at (None: not cut)."""

    problem: Problem
    nominal: Nominal
    fitter: Fitter
    model: Model
    rounds: list[Round]
    tests: tuple[LinearMove, ...]
    cap: Cap | None = None


@dataclass(frozen=True)
class Cap:
    """The longest dead time (s) a search without a model may give the plant, what the dead time found was far
    beyond (``why``, for the progress), the sentence that says so among the identification's constraints and the
    candidates not searched below it."""

    seconds: float
    why: str
    said: str
    leaves_out: frozenset[str] = frozenset()


def _cap(recording: Recording, first: Searched, validation: str, stops: tuple[float, float]) -> Cap | None:
    """The dead-time cap of every search after the first one without a model (None: no cap): the shorter of
    the healthy part's before a located change point
    (:func:`~valve_emulator.diagnosis.explain.onset.delay_cap`) and the set point's bound
    (:func:`~valve_emulator.diagnosis.fit.closed_loop.setpoint_delay`: PV answers the set point's steps within
    m samples, OP answering them at once, so the plant's dead time is shorter than m samples), each only where
    the first search's dead time is far beyond it (:func:`~valve_emulator.diagnosis.explain.onset.far_beyond`),
    and each a sample above it, as the grid's dead times are whole samples."""
    delay = first.model.fit.structure.delay
    caps = []
    healthy = delay_cap(prepare(recording, validation=validation, stops=stops), recording.sp, delay,
                        first.nominal.identification)
    if healthy is not None:
        said = (f"dead time below {healthy:.3g} s: the plant identified on the part before the change point in "
                f"PV's control error (the valve still healthy there, the loop linear) has "
                f"{healthy - first.problem.dt:.3g} s, and the {delay:.3g} s a search found over the whole record "
                f"is far beyond it")
        caps.append(Cap(healthy, "the healthy part's (before the change point)", said=said))
    bound = _setpoint_cap(recording, first)
    if bound is not None:
        caps.append(bound)
    return min(caps, key=lambda c: c.seconds, default=None)


def _prepared(recording: Recording, nom: Nominal | None, lib: dict, say, *, prefilter: float | None,
              validation: str, stops: tuple[float, float], declared: Declared | None = None, reach: int = 1,
              cap: Cap | None = None) -> tuple[Problem, Nominal]:
    """The recording checked and split, the nominal model (identified from the data without one, under the
    closed loop's constraints and what ``declared`` says of the loop, its dead time below ``cap`` when given)
    and the fit part started after every candidate's burn-in."""
    problem = prepare(recording, nominal_delay=nom.delay if nom else None,
                      settle_time=nom.settle_time if nom else 0.0, prefilter=prefilter, validation=validation,
                      stops=stops, reach=reach)
    problem = _bounded_delays(problem, cap.seconds if cap is not None else None)
    if nom is None:
        say("identifying the linear part from the data (FOPDT or IPDT)")
        constraints = identification(problem.op, problem.pv, recording.sp, declared, dt=problem.dt)
        if cap is not None:
            constraints = replace(constraints, constraints=constraints.constraints + (cap.said,))
        problem = _bounded_delays(problem, constraints.delay_bound(True) if constraints.integrating else None)
        nom = identify(problem, constraints=constraints)
    return with_burn_in(problem, library_burn_in(problem, nom, lib)), nom


def held_integrator(nom: Nominal, problem: Problem) -> Nominal:
    """``nom`` with its linear part held (time constants and steady-state gain) when it is a given integrating
    plant; any other nominal as it is.

    Why: a level loop's load wanders at the integrator's input and the controller cancels it with OP, so OP
    is correlated with the disturbance the free run leaves in its residual, and a least-squares (output-error)
    fit of the gain and the lags from that closed loop is biased toward replaying less of OP's answer to the
    load (Forssell & Ljung, *Closed-loop identification revisited*, Automatica 35 (1999) 1215–1241, §3). On the
    independent ``level_sticky`` loops with their exact model the linear part re-fitted around the ideal valve
    went to 0.29 of the nominal gain and a tenth of its lag (draw 32.0), and predicted held-out PV better
    through the prefilter (88.9 %) than the nominal plant driven by the *true* valve position (75.6 %), so no
    valve could count against it. The search therefore keeps the user's integrating plant as given, and the
    linear part moves only by :func:`~valve_emulator.diagnosis.explain.prior.settle`'s test, with the
    drifting-load noise model's BIC among its conditions; each round of the search decides under that noise
    model too (:meth:`~valve_emulator.diagnosis.explain.search.Search.under_load`).
    """
    st = nom.structure
    if not nom.given or not st.integrating or st.fixed_poles:
        return nom
    gain = nominal_gain(nom.num, nom.den)
    if not np.isfinite(gain) or gain == 0.0:
        return nom
    return replace(nom, structure=replace(st, taus_held=True, gain=gain / problem.y_scale))


def _bounded_delays(problem: Problem, bound: float | None) -> Problem:
    """``problem`` with its dead-time grid cut below ``bound`` (s; None: as it is), at least no dead time."""
    if bound is None:
        return problem
    keep = problem.delays[problem.delays * problem.dt < bound]
    return replace(problem, delays=keep if keep.size else problem.delays[:1])


def _search_once(recording: Recording, nom: Nominal | None, lib: dict, say, *, prefilter: float | None,
                 validation: str, stops: tuple[float, float], declared: Declared | None = None,
                 reach: int = 1, cap: Cap | None = None) -> Searched:
    """Prepare, (identify,) search, settle the nominal linear part: one pass in one cost domain (``reach``: see
    :func:`~valve_emulator.diagnosis.fit.data.prepare`; ``cap``: the longest dead time, or None)."""
    problem, nom = _prepared(recording, nom, lib, say, prefilter=prefilter, validation=validation, stops=stops,
                             declared=declared, reach=reach, cap=cap)
    suspected = suspect_onset(problem.pv, recording.sp)
    problem = post_onset_split(problem, suspected)
    # Windows for a long record's coarse stages (fit/windows.py) only with a nominal model and where the loop's
    # behaviour is not located to change part-way: without a model the coarse stage also chooses the poles,
    # up to a tenth of the record, longer than a window; after a change windows would weigh the part after it
    # by how many of them fall there.
    fitter = Fitter(Scorer(problem, held_integrator(nom, problem), lib), windowed=suspected is None and nom.given)
    search = Search(fitter, progress=say, suspected=suspected)
    model, rounds = search.run()
    if nom.given:
        say("testing whether the nominal linear part moves")
    model, tests = settle(search, model)
    return Searched(problem=problem, nominal=nom, fitter=fitter, model=model, rounds=rounds, tests=tests, cap=cap)


def _search(recording: Recording, nom: Nominal | None, lib: dict, say, *, validation: str,
            stops: tuple[float, float], declared: Declared | None = None) -> Searched:
    """The search in the right cost domain (see the module docstring): a nominal integrating plant's on
    prefiltered PV; without a model on PV, once more prefiltered when the result integrates, and once more
    prefiltered with the plant held integrating when it does not and the controller's law was read. Where the
    first pass's dead time is far beyond that of the healthy part before a located change point, or beyond the
    set point's bound, every pass searches it below that one (:func:`_cap`)."""
    dt = recording.dt if len(recording) >= 2 else 1.0
    if nom is not None:
        st = nom.structure
        lam = prefilter_for(st.delay + sum(st.taus), dt) if st.integrating else None
        return _search_once(recording, nom, lib, say, prefilter=lam, validation=validation, stops=stops)
    lib = {k: v for k, v in lib.items() if k != "dead_time"}  # without a nominal model the dead time is identified
    first = _search_once(recording, None, lib, say, prefilter=None, validation=validation, stops=stops,
                         declared=declared)
    cap = _cap(recording, first, validation, stops)
    out = _passes(recording, first, lib, say, validation=validation, stops=stops, declared=declared, cap=cap)
    if cap is None and out.model.fit.structure.delay != first.model.fit.structure.delay:
        # The set point's bound holds for every pass: a dead time the later passes put far beyond it (the
        # first's was within it) is searched below it from the first pass on. The first pass's own dead time
        # was judged in _cap.
        cap = _setpoint_cap(recording, out)
        if cap is not None:
            out = _passes(recording, first, lib, say, validation=validation, stops=stops, declared=declared,
                          cap=cap)
    return out


def _passes(recording: Recording, first: Searched, lib: dict, say, *, validation: str,
            stops: tuple[float, float], declared: Declared | None, cap: Cap | None) -> Searched:
    """The passes after the first one without a model (see :func:`_search`), each below ``cap`` when given,
    without the candidates it leaves out."""
    dt = first.problem.dt
    out = first
    if cap is not None:
        say(f"the dead time is far beyond {cap.why}: searching below {cap.seconds:.3g} s")
        lib = {k: v for k, v in lib.items() if k not in cap.leaves_out}
        out = _search_once(recording, None, lib, say, prefilter=None, validation=validation, stops=stops,
                           declared=declared, cap=cap)
    reach = 1
    if delay_at_end(out.problem, out.model.fit.structure.delay) and widens(out.problem):
        say("the dead time sits on the end of the grid searched: searching again with the grid widened")
        reach = WIDEN
        out = _search_once(recording, None, lib, say, prefilter=None, validation=validation, stops=stops,
                           declared=declared, reach=reach, cap=cap)
    st = out.model.fit.structure
    if st.integrating:
        say("the plant integrates: searching again on prefiltered PV")
        out = _search_once(recording, None, lib, say, prefilter=prefilter_for(st.delay + sum(st.taus), dt),
                           validation=validation, stops=stops, declared=declared, reach=reach, cap=cap)
    ident = replace(out.nominal.identification, integrating=True)
    if (out.model.fit.structure.integrating or (declared is not None and declared.plant_integrates is not None)
            or ident.max_delay is None):
        return out
    say("searching again on prefiltered PV, the plant held integrating")
    ipdt = identify(_bounded_delays(out.problem, ident.delay_bound(True)), constraints=ident).structure
    held = _search_once(recording, None, lib, say, prefilter=prefilter_for(ipdt.delay, dt),
                        validation=validation, stops=stops,
                        declared=replace(declared or Declared(), integrating=True), reach=reach, cap=cap)
    return _integrating_or_not(out, held)


def _setpoint_cap(recording: Recording, searched: Searched) -> Cap | None:
    """The set point's cap (:func:`_cap`) of a pass's dead time, alone: None where it is not far beyond.

    The actuator-lag candidate is not searched below it: the pass's dead time stood in for a lag between OP and
    PV that its plant of one time constant could not hold, and a lag found once that dead time is taken away is
    the plant's as well as the actuator's — OP and PV do not tell them apart."""
    dt, delay = searched.problem.dt, searched.model.fit.structure.delay
    m = setpoint_delay(recording.pv, recording.sp, int(delay / dt))
    if m is None or not far_beyond(delay, m * dt, dt):
        return None
    said = (f"dead time below {m * dt:.3g} s: PV answers the set point's steps within {m} samples (its step "
            f"response from the set point, refuted as none from the {delay:.3g} s a search found down to {m} "
            f"samples, a closed test at {100 * SETPOINT_LEVEL:g} %), and OP answers them at once")
    return Cap((m + 1) * dt, "the set point's bound", said=said, leaves_out=frozenset({"actuator_lag"}))


def _integrating_or_not(free: Searched, held: Searched) -> Searched:
    """The search so far (``free``, whose plant came out self-regulating) or the one on prefiltered PV that held
    the plant integrating (``held``): the held one when its held-out fit, cross-validated through the prefilter,
    beats the free one's on the same blocks in the same domain by :data:`DELTA_FIT` points, it explains PV
    better under the drifting-load noise model by :data:`DELTA_BIC`
    (:func:`~valve_emulator.diagnosis.fit.load_check.family_delta_bic`), and its gain is not held at zero by the
    gain's sign.

    Why: on PV an integrator's free run drifts with every wandering load, so the search there prefers a slow
    first-order plant or a half-cycle dead time, and a sticky level valve goes unseen; through the prefilter
    the load is forgotten, and the two families are compared on what each predicts of the loop's cycles. The
    prefilter alone would give a self-regulating loop an integrator (it forgets the slow response such a plant
    predicts), so both are also scored on PV itself, as one-step predictions under a random-walk load: there a
    first-order flow loop keeps its plant, while the free run of PV, which no integrating model can match on a
    loop whose load wanders, would reject a level loop's right plant as readily.

    The integrator must also be a plant on its own: when its linear part (no candidate) explains PV under that
    noise model worse than the free family's linear part by more than :data:`HELD_LINEAR_LOSS`, the held search
    won through its candidates, which then stand in for the plant (a first-order flow loop under a sinusoidal
    load was held integrating, and a stiction with J twice S fitted the load's cycle).
    """
    ours = with_cv(held.fitter.scorer, held.model).heldout
    theirs = cross_validated_fit(held.fitter.scorer, free.model)
    if not ours >= theirs + DELTA_FIT or held.model.fit.gain == 0.0:
        return free
    better = family_delta_bic((free.fitter.scorer, free.model), (held.fitter.scorer, held.model))
    if not better >= DELTA_BIC:
        return free
    if family_delta_bic((free.fitter.scorer, _base(free)), (held.fitter.scorer, _base(held))) < -HELD_LINEAR_LOSS:
        return free
    ident = held.nominal.identification
    said = tuple(c for c in ident.constraints if "plant (declared)" not in c) + (
        f"integrating plant: through the high-pass prefilter, the search holding an integrator predicts held-out "
        f"PV better than the search with the family free ({ours:.1f} % against {theirs:.1f} %), and under a "
        f"drifting-load noise model it explains PV better (ΔBIC {better:.0f})",)
    nominal = replace(held.nominal, identification=replace(ident, integrating=None, constraints=said))
    return replace(held, nominal=nominal)


def _base(s: Searched) -> Model:
    """The linear model a search started from (its first round's baseline; the final model without rounds)."""
    return s.rounds[0].baseline if s.rounds else s.model


def _before(s: Searched, base: Model) -> tuple[np.ndarray, float, int]:
    """PV of the model the diagnosis starts from (the nominal replay, or the identified base model), its
    held-out fit and where the held-out part starts."""
    problem = s.problem
    test_start = problem.test[0] if problem.validation == "split" else held_out_start(problem.T)
    if not s.nominal.given:
        return problem.to_pv(base.y_hat), _reported_fit(s, base), test_start
    pv_before = _replay_nominal(problem, s.nominal, s.fitter.scorer)
    return pv_before, fit_percent(problem.pv[test_start:], pv_before[test_start:]), test_start


def _reported_fit(s: Searched, model: Model) -> float:
    """The held-out fit of ``model`` as reported, on PV itself. The search's rule compared it in the problem's
    validation domain (:meth:`~valve_emulator.diagnosis.fit.data.Problem.validated`), which differs from PV
    only for an integrating plant's prefiltered search."""
    problem = s.problem
    if problem.prefilter is None:
        return model.heldout
    if problem.validation == "split":
        return problem.pv_heldout_fit(model.y_hat)
    return cross_validated_fit(s.fitter.scorer, model, on_pv=True)


def _response_horizon(problem: Problem, model: Model) -> float:
    """How long the final model takes to answer an OP move (s): dead time plus twice the time constants, at
    least ten samples; residuals are located and windows measured on this scale."""
    st = model.fit.structure
    return max(st.delay + 2.0 * sum(st.taus), 10.0 * problem.dt)


def _ranking(rounds: list[Round], frame: Frame) -> tuple[RankRow, ...]:
    """Every option of every round, in the order tried, with its ΔBIC against the round's baseline."""
    return tuple(RankRow(round=i + 1, option=o.label, parameters=param_text(o.model, o.added, frame),
                         delta_bic=rnd.baseline.bic - o.model.bic, heldout=o.model.heldout, chosen=o is rnd.chosen)
                 for i, rnd in enumerate(rounds) for o in rnd.options)


def _traces(s: Searched, base: Model, pv_before: np.ndarray, test_start: int, frame: Frame) -> Traces:
    """The signals of the figure, OP and flow in OP's units: recorded, nominal, base and final PV, the valve's
    position alone (linear characteristic) and the stiction scan's ΔBIC surface."""
    problem, model, nom = s.problem, s.model, s.nominal
    ctx = s.fitter.scorer.ctx(model)
    valve_only = {k: v for k, v in model.by_slot().items() if k in ("actuator", "valve")}
    mv = run_chain(problem.op, valve_only, replace(ctx, characteristic=("linear", DEFAULT_RANGEABILITY)),
                   nominal_valve=(nom.S, nom.J))[:, 0]
    surface, surface_best, surface_load_model = stiction_surface(s.rounds)
    if surface is not None and not frame.identity:
        surface = (surface[0] / frame.gain, surface[1] / frame.gain, surface[2])
        surface_best = (surface_best[0] / frame.gain, surface_best[1] / frame.gain)
    back = frame.from_internal
    return Traces(t=problem.t, op=back(problem.op), pv=problem.pv, pv_before=pv_before,
                  pv_base=problem.to_pv(base.y_hat), pv_after=problem.to_pv(model.y_hat),
                  mv_after=back(mv), flow_after=back(model.flow),
                  test_start=test_start, surface=surface, surface_best=surface_best,
                  surface_load_model=surface_load_model)


def _fitted(s: Searched, frame: Frame, model: Model | None = None) -> FittedLoop:
    """The final model (or another ``model`` of the search) as a loop that replays any OP."""
    problem, nom = s.problem, s.nominal
    model = s.model if model is None else model
    return FittedLoop(active=model.by_slot(), nominal_valve=(nom.S, nom.J), ctx=s.fitter.scorer.ctx(None),
                      linear=model.fit, level=float(np.mean(model.flow)), record_length=problem.T, op=problem.op,
                      frame=None if frame.identity else frame)


def _valve_alternative(s: Searched, frame: Frame, least_band: float) -> ValveAlternative | None:
    """The option of the search with the lowest BIC that adds valve friction (a candidate of the valve slot with a
    band S) with S at least ``least_band`` (OP's units), scored against the final model under the drifting-load
    noise model (None when the search tried none): the valve as the alternative a "no stiction" answer must beat."""
    tried = [(o.model, a) for rnd in s.rounds for o in rnd.options for a in o.model.active
             if a.name in o.added and a.candidate.slot == "valve" and "S" in a.candidate.param_names]
    sized = [(m, a, frame.convert(a.candidate.dims, a.candidate.parameters(a.params))) for m, a in tried]
    sized = [(m, a, p) for m, a, p in sized if p["S"] >= least_band]
    if not sized:
        return None
    model, act, params = min(sized, key=lambda x: x[0].bic)
    load = load_delta_bic(s.fitter.scorer, s.model, model)
    if not (load >= DELTA_BIC and not _friction_that_matters(s.model, frame, least_band)):
        return ValveAlternative(physics=act.name, S=float(params["S"]), J=float(params.get("J", 0.0)),
                                load_delta_bic=load)
    # the answer may rest on it: its intervals as a finding's, its model for the twin, and whether PV shows its
    # band's memory beyond any characteristic
    own, _ = parameter_intervals(s.fitter, s.problem, model, act, act.candidate.parameters(act.params))
    ivs = {k: v for k, v in frame.convert(act.candidate.dims, own).items() if k in ("S", "J")}
    return ValveAlternative(physics=act.name, S=float(params["S"]), J=float(params.get("J", 0.0)),
                            load_delta_bic=load, intervals=ivs, fitted=_fitted(s, frame, model),
                            memory=_memory(s, model))


def _friction_that_matters(model: Model, frame: Frame, least_band: float) -> bool:
    """Whether ``model`` holds valve friction with a band of at least ``least_band`` (OP's units): the decision
    reads a smaller band as no friction that could matter (a band inside OP's noise), so its valve alternative
    is then asked as on a model without one."""
    return any(a.candidate.slot == "valve" and "S" in a.candidate.param_names
               and frame.convert(a.candidate.dims, a.candidate.parameters(a.params))["S"] >= least_band
               for a in model.active)


def _memory(s: Searched, model: Model) -> Memory:
    """Whether PV shows the memory of ``model``'s valve band beyond any single-valued map of OP
    (:func:`~valve_emulator.diagnosis.fit.load_check.remembered`): the valve's output alone (its actuator and
    valve slots, a linear characteristic) through ``model``'s plant, on the fit part."""
    problem = s.problem
    valve_only = {k: v for k, v in model.by_slot().items() if k in ("actuator", "valve")}
    ctx = replace(s.fitter.scorer.ctx(model), characteristic=("linear", DEFAULT_RANGEABILITY))
    mv = run_chain(problem.op, valve_only, ctx, nominal_valve=(s.nominal.S, s.nominal.J))[:, 0]
    return remembered(problem.pv, problem.op, mv, model.fit.structure, problem.dt, problem.train[0])


@one_blas_thread
def explain(recording: Recording, nominal: LoopConfig | None = None, *,
            candidates: Sequence[str] | None = None,
            progress: Callable[[str], None] | None = None, validation: str | None = None,
            frame: Frame | None = None, declared: Declared | None = None,
            least_band: float | None = None) -> Explanation:
    """Explain what the nominal model leaves out (see the module docstring).

    Parameters
    ----------
    recording : ``t``, ``op``, ``pv`` are used (``sp`` and ``mv`` may be absent).
    nominal : the loop the user believes in; None identifies a linear model (FOPDT or IPDT) from the data.
    candidates : names from the candidate registry (default: all); ``dead_time`` needs a nominal model.
    progress : called with a short message at each stage (the CLI prints them on stderr).
    validation : ``"split"`` or ``"twofold"`` (default: split with a nominal model, two-fold without).
    frame : when ``recording.op`` was mapped into a unit-free frame
        (:meth:`~valve_emulator.diagnosis.fit.frame.Frame.to_internal`), that map: findings, the plant's gain,
        the traces and :meth:`~Explanation.predict` are then in OP's own units. Default: OP is % travel.
    declared : without a nominal model, what the user declares about the loop (its type, whether the plant
        integrates, the controller's action; :class:`~valve_emulator.diagnosis.fit.closed_loop.Declared`).
    least_band : with two-fold validation, the least valve band S (OP's units) that could matter: the best valve
        option the search tried with at least that band is kept as :attr:`Explanation.valve_alternative`.

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
    frame = frame or Frame()
    s = _search(recording, nominal_from_config(nominal, dt) if nominal is not None else None, lib, say,
                validation=validation, stops=frame.stops, declared=declared)
    problem, nom, model, rounds = s.problem, s.nominal, s.model, s.rounds
    base = rounds[0].baseline if rounds else model
    pv_before, fit_before, test_start = _before(s, base)
    horizon = _response_horizon(problem, model)
    masks = condition_masks(problem.op, w=max(3, int(round(horizon / problem.dt / 2))),
                            horizon=max(2, int(round(horizon / problem.dt))))
    located = locate(problem.t, problem.op, (problem.pv - pv_before) ** 2, dt=problem.dt,
                     response_time=horizon, masks=masks)
    say("estimating parameter intervals")
    found = findings(s.fitter, problem, model, rounds, masks, horizon, nom, frame)
    found = acting_part(problem, model, pv_before, found)
    st = model.fit.structure
    # A grid cut at a cap ends below the dead time the data allow, not at an open edge.
    delay_is_bound = not nom.given and s.cap is None and delay_at_end(problem, st.delay)
    plant = {"gain": model.fit.gain * problem.y_scale * frame.gain, "taus": tuple(st.taus), "delay": st.delay,
             "integrating": st.integrating, "validation": problem.validation, "delay_is_bound": delay_is_bound}
    return Explanation(source=problem.source, given=nom.given, fit_before=fit_before, fit_base=_reported_fit(s, base),
                       fit_after=_reported_fit(s, model), findings=found, located=located,
                       linear=_linear_table(nom, model, problem, frame, delay_is_bound),
                       ranking=_ranking(rounds, frame),
                       traces=_traces(s, base, pv_before, test_start, frame),
                       rule=RULE if validation == "split" else RULE_TWOFOLD, seconds=time.perf_counter() - start,
                       plant=plant, fitted=_fitted(s, frame),
                       input_delta_bic=input_delta_bic(s.fitter.scorer, model) if validation == "twofold" else None,
                       linear_tests=s.tests + dead_time_move(found, nom.delay, st.delay),
                       identification=None if nom.identification is None else {
                           **nom.identification.as_dict(), "delay_searched": float(problem.delays.max()) * problem.dt,
                           "delay_is_bound": delay_is_bound},
                       valve_alternative=(_valve_alternative(s, frame, least_band)
                                          if least_band is not None and validation == "twofold" else None))
