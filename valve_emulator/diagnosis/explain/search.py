r"""Forward selection of left-out physics: Hammerstein fits on a global grid, ranked by BIC and held-out fit.

One round
---------
For every candidate not yet in the model (one per chain slot), the whole coarse parameter grid is pushed
through the chain at once (``(T, n)`` signals), filtered once per linear structure, and the linear part is
fitted by least squares for every grid row *and every dead time* of the delay grid in one compiled call
(:func:`~valve_emulator.diagnosis.fit.linear.delay_grid_sse`). The best row is then refined twice on the
candidate's finer grid, each time followed by a Nelder–Mead polish of the poles (and of a free dead time).

The dead time is searched jointly with every candidate's parameters (a wrong dead time passes for less slip
jump). While the nominal dead time is still trusted, each candidate yields two options: with θ
held at its nominal value, and together with ``dead_time`` (θ free). ``dead_time`` alone is a third kind of
option.

Significance (defined once, here, for every recording)
------------------------------------------------------
An option is *significant* against a smaller model when both

* BIC falls by at least :data:`DELTA_BIC` (BIC = N ln σ̂² + k ln N on the fit part; 10 is "very strong"
  evidence on the Kass & Raftery (1995) scale, a Bayes factor above about 150), and
* the free-run fit on the held-out part rises by at least :data:`DELTA_FIT` percentage points.

Threshold parameters sit on boundaries, so likelihood-ratio tests do not apply; the held-out
free-run test guards against fitting noise. The round accepts the option with the lowest BIC that is
significant against the current model *and* against each of its own sub-options (so "stiction + dead time"
is accepted only if both parts carry weight). Rounds repeat until no option is significant.

With ``validation="twofold"`` (no nominal model, :mod:`~valve_emulator.diagnosis.fit.data`) BIC is computed on
the whole record and the held-out fit is the pooled two-fold cross-validated fit
(:mod:`~valve_emulator.diagnosis.fit.crossval`); it is computed only for the models a significance test needs
(options whose BIC already passes, their sub-options and the current model) and is NaN for the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from valve_emulator.diagnosis.candidates.base import Candidate, Kind
from valve_emulator.diagnosis.explain.onset import (
    LateOnset,
    Suspected,
    before_part,
    bic_after,
    bic_on,
    late_options,
    late_start,
    onset_option,
    throughout,
)
from valve_emulator.diagnosis.fit.crossval import with_cv
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.load_check import load_bic, load_bic_on
from valve_emulator.diagnosis.fit.records import Model, Option, Surface

__all__ = ["DELTA_BIC", "DELTA_FIT", "Model", "Surface", "Option", "Round", "Search", "significant"]

#: Least BIC decrease for an addition to count (see the module docstring).
DELTA_BIC = 10.0
#: Least held-out free-run fit gain, percentage points, for an addition to count.
DELTA_FIT = 0.5


@dataclass(frozen=True, eq=False, kw_only=True)
class Round:
    """One round of the search: the model it extended, every option (sorted by BIC) and the one accepted."""

    baseline: Model
    options: tuple[Option, ...]   # sorted by BIC
    chosen: Option | None


def significant(new: Model, old: Model) -> bool:
    """The significance rule of the module docstring."""
    return (old.bic - new.bic >= DELTA_BIC) and (new.heldout - old.heldout >= DELTA_FIT)


class Search:
    """Runs the rounds for one problem (a fitting machine; its results are :class:`Round` objects).

    It *has* a :class:`~valve_emulator.diagnosis.fit.fitter.Fitter`, which has the
    :class:`~valve_emulator.diagnosis.fit.scorer.Scorer` of the problem; ``progress`` is called with a short
    message at each stage.
    """

    def __init__(self, fitter: Fitter, *, progress: Callable[[str], None] | None = None,
                 suspected: Suspected | None = None) -> None:
        self.fitter = fitter
        self.suspected = suspected
        self.scorer = fitter.scorer
        self.say = progress or (lambda msg: None)

    def _candidates(self, model: Model) -> list[Candidate]:
        used = set(model.by_slot())
        out = []
        for cand in self.scorer.library.values():
            if cand.slot in used or cand.kind is Kind.LOOP:
                continue
            if cand.slot == "delay" and model.delay_free:
                continue
            out.append(cand)
        return out

    def validated(self, model: Model) -> Model:
        """``model`` with a held-out fit (two-fold validation computes it on demand)."""
        return model if self.scorer.p.validation == "split" else with_cv(self.scorer, model)

    def late_onsets(self, model: Model, cand: Candidate, options: list[Option]) -> list[Option]:
        """``options``, where physics that may start part-way acts from a fitted onset on
        (:mod:`~valve_emulator.diagnosis.explain.onset`).

        Where no change point was located before the search, the late option replaces the whole-record one
        when it lowers BIC by at least twice :data:`DELTA_BIC`: the onset is then searched over the record,
        and the best of many positions gains likelihood from noise alone more than one parameter does. Where
        one was not, the part before the onset must also show the valve healthy there (:meth:`healthy_before`):
        the onset was placed where the fit part gains most, so that gain is no evidence of its own. Where
        one was (``suspected``), the onset is searched only near it and the late option joins the options,
        fitted twice: in the free run and through the drifting-load noise model's prefilter
        (:func:`~valve_emulator.diagnosis.explain.onset.late_options`); which one stands for the physics,
        and which other options stay beside it, the round decides (:meth:`late_first`)."""
        single = next((o for o in options if o.added == (cand.name,)), None)
        if single is None:
            return options
        if self.suspected is None:
            late = onset_option(self.fitter, model, cand, single)
            if (late is None or single.model.bic - late.model.bic < 2 * DELTA_BIC
                    or not self.healthy_before(late.model, single.model, model)):
                return options
            return [late if o is single else o for o in options]
        return [*options, *(o for o in late_options(self.fitter, model, cand, single, self.suspected) if o is not None)]

    def _starts_late(self, option: Option) -> bool:
        return any(isinstance(a.candidate, LateOnset) for a in option.model.active if a.name in option.added)

    def _may_start_late(self, option: Option) -> bool:
        return any(getattr(self.scorer.library.get(name), "may_start_late", False) for name in option.added)

    def late_first(self, options: list[Option], model: Model) -> tuple[list[Option], Option | None]:
        """Where an onset was located and the best late option counts against ``model`` (:meth:`late_counts`),
        ``options`` without the options that do not beat it (:meth:`whole_beats_late`), and that late option
        (validated); else ``options`` as they are and None. A late option that does not count replaces nothing.

        Before a valve starts to stick the loop's OP moves little, so a valve sticking throughout, or a
        deadband, fits the healthy part about as well, and BIC alone cannot ask for the onset; a dead time
        freed to let a valve that sticks throughout fit the healthy part is not evidence of either. Nor is any
        other addition that mends only what the free run makes of the wandering load: before the onset the
        controller cancels the load with OP while PV holds its set point, and an addition that shrinks the
        linear part's answer to OP (a dead time, a slow disturbance, a saturation) gains there what the late
        valve cannot. So every other option must beat the late one the way a whole-record valve must. Of the
        late options that count, each physics (a sticky valve, a deadband) is fitted twice, in the search's domain
        and under the drifting-load noise model (:func:`~valve_emulator.diagnosis.explain.onset.
        late_options`, the nominal linear part among its starts); of the two, the one with the better
        held-out fit stands for the physics (the held-out part lies after the onset,
        :func:`~valve_emulator.diagnosis.explain.onset.post_onset_split`), and of the physics the one with the
        lowest BIC leads; the other late options are dropped. Why held-out fit between the two fits of one
        physics: BIC prefers the fit whose linear part leans on the load (draw 4 of the property test with its
        model: a late valve of J 5.3 % around a gain shrunk to 0.4 of the nominal one, 237 lower in BIC, against J
        3.8 % (truth 3.7 %) around the nominal linear part, held-out fit 30 % against 48 %)."""
        lates = sorted((o for o in options if self._starts_late(o)), key=lambda o: o.model.bic)
        if self.suspected is None or not lates:
            return options, None
        counted = [(o, replace(o, model=self.validated(o.model))) for o in lates]
        counted = [(o, v) for o, v in counted if self.late_counts(v.model, model)]
        if not counted:
            return options, None
        stands = {}
        for c in counted:   # per physics, the fit that predicts the held-out part best
            kept = stands.get(c[1].added)
            if kept is None or (c[1].model.heldout, -c[1].model.bic) > (kept[1].model.heldout, -kept[1].model.bic):
                stands[c[1].added] = c
        first, best = min(stands.values(), key=lambda c: c[1].model.bic)
        if not self.shows_onset(best.model, model):
            return [o for o in options if o not in lates], None
        whole = next((o for o in options if o.added == best.added and o not in lates), None)
        whole = None if whole is None else replace(whole, model=self.validated(whole.model))
        if not self.onset_evidenced(best.model, whole, model):
            return [o for o in options if o not in lates], None
        out = []
        for o in options:
            if o is first:
                out.append(best)
            elif o in lates:
                continue   # the lead stands for the late physics
            else:
                other = whole if whole is not None and o.added == whole.added else replace(
                    o, model=self.validated(o.model))
                if self.whole_beats_late(other.model, best.model):
                    out.append(other)
        dropped = {frozenset(o.added) for o in options} - {frozenset(o.added) for o in out}
        return [o for o in out if not any(d < frozenset(o.added) for d in dropped)], best  # its parts too

    def shows_onset(self, late: Model, model: Model) -> bool:
        """Whether the record shows a healthy part before ``late``'s onset: at least :data:`~valve_emulator.
        diagnosis.explain.onset.MIN_BEFORE` of the record between where the linear part has settled from its
        unknown initial state (its dead time and five of its longest time constants, as
        :func:`~valve_emulator.diagnosis.explain.onset.before_part`) and the onset.

        Why: before that the fit cannot tell a valve that starts to stick there from one that sticks from the
        start, and the change point that located the onset is then where the loop starts to cycle, not where
        the valve starts to stick. A valve that sticks from the first sample, in a loop at rest until its set
        point moves, does not slip before the controller's integral has moved OP through the band: the loop's
        control error steps up at the first slip. The README's concentration loop (S = 5 %, J = 2 % throughout,
        1,500 s, a set-point step at 10 s) was answered as sticking "from t ≈ 67.5 s on", 7 s after its linear
        part had settled (10 s dead time, 10 s lag). Where the record does not show the onset, the late options
        are withdrawn and the whole-record ones compete by the search's usual rule."""
        t0 = late_start(late)
        return t0 is None or self._before_onset(t0, late, model) is not None

    def _before_onset(self, t0: float, late: Model, model: Model) -> tuple[int, int] | None:
        """The part of the record before ``late``'s onset at ``t0`` s that :meth:`shows_onset` and
        :meth:`healthy_before` judge (:func:`~valve_emulator.diagnosis.explain.onset.before_part`; None: shorter
        than :data:`~valve_emulator.diagnosis.explain.onset.MIN_BEFORE` of the record)."""
        p = self.scorer.p
        return before_part(p, int(round(t0 / p.dt)), late, model)

    def onset_evidenced(self, late: Model, whole: Option | None, model: Model) -> bool:
        """Whether the record shows the located onset of ``late`` against the same physics acting throughout
        (``whole``, the round's whole-record option of it, validated; True without one): the late option counts
        against it on the fit part by the rule by which it counts against ``model`` (:meth:`late_counts`), or
        the part before the onset shows the valve healthy there (:meth:`healthy_before`).

        Why: a late valve's claim is that the part before its onset shows a healthy valve. Where the onset lies
        before the fit part, or the valve's state has forgotten it by then, the late option and the whole-record
        one are the same model there, and BIC cannot choose between them (the onset's parameter costs ln N);
        every other option had to beat the late lead, so such a tie went to the onset. Measured on the shared
        draws of ``tests/unseen_loops.py`` (2026-11-27): a sticky flow loop with its model (valve sticking
        throughout) was answered "from t ≈ 390 s on", the late option 28 *higher* in BIC than the whole-record
        one on the fit part and the part before the onset 908 lower in BIC with the valve sticking there."""
        if whole is None or self.late_counts(late, whole.model):
            return True
        return self.healthy_before(late, whole.model, model)

    def healthy_before(self, late: Model, whole: Model, model: Model) -> bool:
        """Whether the part before ``late``'s onset (:func:`~valve_emulator.diagnosis.explain.onset.before_part`,
        as :meth:`shows_onset` judges it) prefers the healthy valve there to a valve sticking throughout, by
        :data:`DELTA_BIC`: its BIC on that part (AR(1) error, :func:`~valve_emulator.diagnosis.explain.onset.
        bic_on`), or its BIC there under the drifting-load noise model (:func:`~valve_emulator.diagnosis.fit.
        load_check.load_bic_on`, the linear part re-fitted on that part), at least 10 below that of both valves
        sticking throughout: ``whole`` (the whole-record fit of the physics) and ``late``'s own valve acting
        from the record's start (:func:`~valve_emulator.diagnosis.explain.onset.throughout`). False where that
        part is shorter than :data:`~valve_emulator.diagnosis.explain.onset.MIN_BEFORE` of the record.

        Why both valves: each alone leaves a valve sticking throughout that the healthy one does not beat on
        the shared draws — the whole-record fit of a sticky level loop as plant data (valve sticking throughout,
        answered "from 360 s on") fits the part before the onset 14 worse than the healthy valve, the late
        valve acting from the start 119 better; on a sticky flow loop with its model the late valve acting from
        the start is 240 worse under the drifting-load noise model, the whole-record fit 800 better. Why either
        noise model: before the onset the controller cancels a wandering load with OP while PV holds its set
        point, which the free run's AR(1) residual reads as the valve's doing (:meth:`late_counts`); on the
        ``late_onset`` property draws whose onset lies before the fit part the healthy valve is preferred under
        the drifting-load noise model alone (draw 6 as plant data: by 18)."""
        t0 = late_start(late)
        window = None if t0 is None else self._before_onset(t0, late, model)
        if window is None:
            return False
        p = self.scorer.p
        rivals = (whole, throughout(self.scorer, late))
        own = bic_on(p, late, window)
        if all(bic_on(p, r, window) - own >= DELTA_BIC for r in rivals):
            return True
        own = load_bic_on(self.scorer, late, window)[0]
        return all(load_bic_on(self.scorer, r, window)[0] - own >= DELTA_BIC for r in rivals)

    def lower_under_load(self, new: Model, old: Model) -> bool:
        """Whether ``new``'s BIC under the drifting-load noise model (:func:`~valve_emulator.diagnosis.fit.
        load_check.load_bic`) is at least :data:`DELTA_BIC` below ``old``'s."""
        return load_bic(self.scorer, old)[0] - load_bic(self.scorer, new)[0] >= DELTA_BIC

    def late_counts(self, late: Model, model: Model) -> bool:
        """Whether a late option (its onset located before the search) counts against ``model``: by the
        significance rule, or by a BIC :data:`DELTA_BIC` lower under the drifting-load noise model.

        Why the second: the free run cannot judge a valve that starts late under a wandering load. Before the
        onset the controller moves OP to cancel the load while PV holds its set point; the free run replays
        those moves into PV swings that never happened, and the linear part fitted around the healthy valve
        shrinks its gain to replay less of them (on the independent ``late_onset`` loops with their model, to
        a seventh of the nominal gain, for a held-out fit of 76 % against 19 % for the loop's own late valve
        at its true S, J and onset). Under the drifting-load noise model the load is allowed for, and the
        true late valve is the better model (draw 6 of the property test: BIC 12 to 24 lower than the healthy
        valve with the shrunk gain)."""
        return significant(late, model) or self.lower_under_load(late, model)

    def holds_after_onset(self, new: Model, old: Model) -> bool:
        """Where ``old`` has a finding that starts late, whether ``new`` also lowers the BIC of the part after
        its onset by :data:`DELTA_BIC` (:func:`~valve_emulator.diagnosis.explain.onset.bic_after`), and its BIC
        under the drifting-load noise model by as much: an addition is judged where the late finding acts, not
        credited with the part before it, nor with what the free run makes of a wandering load there."""
        t0 = late_start(old)
        if t0 is None:
            return True
        p = self.scorer.p
        start = int(round(t0 / p.dt))
        return bic_after(p, old, start) - bic_after(p, new, start) >= DELTA_BIC and self.lower_under_load(new, old)

    def holds_before_onset(self, new: Model, old: Model) -> bool:
        """Where ``old`` has a finding that starts late, whether ``new`` also fits the healthy part before its
        onset no worse: a BIC there (:func:`~valve_emulator.diagnosis.explain.onset.bic_on` on
        :func:`~valve_emulator.diagnosis.explain.onset.before_part`) no higher than ``old``'s. True where that
        part is too short to judge.

        Why: only a valve's friction starts late; what is added beside it (a dead time, a lag, a
        characteristic, a saturation, a load) is the loop's throughout and acts on the healthy part too. An
        addition that pays for itself after the onset and loses before it mends the late valve's cycles, not
        the loop. Measured on the ``late_onset`` property draws (seed 32): the extra findings accepted beside a
        late valve on draws whose valve alone holds (a slow disturbance for the wandering load, a saturation
        or a dead time beside a Karnopp stem, an equal-percentage characteristic at its range's edge) each
        raised the BIC before the onset, by 2 to 70; the two that lowered it (a dead time beside the valve's
        own actuator lag, the plant's second lag as an actuator lag) lowered it by 17 and 71 and stay.
        """
        t0 = late_start(old)
        if t0 is None:
            return True
        p = self.scorer.p
        start = int(round(t0 / p.dt))
        window = before_part(p, start, old, new)
        return window is None or bic_on(p, new, window) <= bic_on(p, old, window)

    def whole_beats_late(self, whole: Model, late: Model) -> bool:
        """Whether another option beats the late one where an onset was located: :func:`significant`
        against it, and its BIC under the drifting-load noise model at least :data:`DELTA_BIC` lower too.

        Why both: the search's free-run cost expects PV to come back to what OP explains. Before the onset the
        controller moves OP to cancel a wandering load while PV holds its set point, so a healthy valve replays
        those moves into PV swings that never happened, and a valve stuck there replays them away: on the
        independent ``late_onset`` loops the whole-record valve won by hundreds of BIC on that part alone.
        Under the drifting-load noise model the load is allowed for, and a valve sticking throughout no longer
        gains from it."""
        if not significant(whole, late):
            return False
        return self.lower_under_load(whole, late)

    def round(self, model: Model, index: int) -> Round:
        """Every option that extends ``model`` by one candidate, and the one the rule accepts (if any)."""
        options: list[Option] = []
        cands = self._candidates(model)
        for c, cand in enumerate(cands):
            self.say(f"round {index}: {cand.name} ({c + 1}/{len(cands)})")
            options += self.late_onsets(model, cand, self.fitter.evaluate(model, cand))
        model = self.validated(model)
        options, ahead = self.late_first(options, model)
        options.sort(key=lambda o: o.model.bic)
        if ahead is None and self.held_integrator:
            return Round(baseline=model, options=tuple(options), chosen=self.under_load(options, model))
        chosen = None
        for i, o in enumerate(options):
            if ahead is not None and o.model is ahead.model:
                chosen = o   # it counts (late_counts), and no option before it beat it
                break
            if model.bic - o.model.bic < DELTA_BIC:
                continue  # cannot count whatever its held-out fit (and needs no cross-validation)
            subs = [j for j, s in enumerate(options) if set(s.added) < set(o.added)]
            for j in [i, *subs]:
                options[j] = replace(options[j], model=self.validated(options[j].model))
            o = options[i]
            if (significant(o.model, model) and all(significant(o.model, options[j].model) for j in subs)
                    and self.holds_after_onset(o.model, model) and self.holds_before_onset(o.model, model)):
                chosen = o
                break
        return Round(baseline=model, options=tuple(options), chosen=chosen)

    @property
    def held_integrator(self) -> bool:
        """Whether the linear part is a given integrating plant, held
        (:func:`~valve_emulator.diagnosis.explain.pipeline.held_integrator`)."""
        nom = self.fitter.nominal
        return bool(nom.given and nom.structure.integrating and nom.structure.gain is not None)

    def under_load(self, options: list[Option], model: Model) -> Option | None:
        """The option a round accepts on a held integrating plant: of those that lower BIC by :data:`DELTA_BIC`
        (the search's domain) and BIC under the drifting-load noise model by as much, against ``model`` and
        against each of their own sub-options, the one lowest under that noise model (validated); None if none.
        Beside a finding that starts late, an option must also hold after its onset and before it, as in every
        round (:meth:`holds_after_onset`, :meth:`holds_before_onset`).

        Why the drifting-load noise model decides here, not the free run's held-out fit: the free run of an
        integrator replays every wandering load the record holds as a ramp, and through the prefilter it still
        rewards what replays OP's answer to the load, not what moves the valve. On the independent
        ``level_sticky`` loops with their exact model (draw 7.0.0), the sticky valve at S 5.34, J 4.98 (truth
        5.37, 5.13) lowered the BIC under the drifting-load noise model by 290 and its free-run held-out fit
        was 22 %; an equal-percentage characteristic with no dead time, 106 and 82 %: the free-run rule took
        the characteristic. The one-step predictor with a random-walk load is the noise model of a level loop
        (as :func:`~valve_emulator.diagnosis.fit.load_check.family_delta_bic` uses it to choose the family)."""
        fall = [o for o in options if model.bic - o.model.bic >= DELTA_BIC]   # only these can count
        if not fall:
            return None

        for o in sorted(fall, key=lambda o: load_bic(self.scorer, o.model)[0]):   # remembered per model
            subs = [s for s in options if set(s.added) < set(o.added)]
            if (self.lower_under_load(o.model, model) and all(self.lower_under_load(o.model, s.model) for s in subs)
                    and self.holds_after_onset(o.model, model) and self.holds_before_onset(o.model, model)):
                return replace(o, model=self.validated(o.model))
        return None

    def run(self) -> tuple[Model, list[Round]]:
        """Base model, then rounds while an option is significant. Returns (final model, rounds)."""
        self.say("fitting the linear part around the nominal chain")
        model = self.validated(self.fitter.base())
        rounds = []
        while self._candidates(model):
            rnd = self.round(model, len(rounds) + 1)
            rounds.append(rnd)
            if rnd.chosen is None:
                break
            self.say(f"round {len(rounds)}: added {rnd.chosen.label} (BIC {model.bic - rnd.chosen.model.bic:.0f} "
                     f"lower, held-out fit {model.heldout:.1f} -> {rnd.chosen.model.heldout:.1f} %)")
            model = self.validated(self.rerefine(rnd.chosen.model, rnd.chosen.added))
        return model, rounds

    def rerefine(self, model: Model, just_added: tuple[str, ...] = (), only: set[str] | None = None) -> Model:
        """Refine earlier-accepted grid physics again with the new one in place; keep it if BIC improves."""
        aim = self.scorer.aim(model)
        for a in model.active:
            if a.name in just_added or a.slot == "delay" or a.candidate.kind is not Kind.CHAIN:
                continue
            if only is not None and a.name not in only:
                continue
            rest = replace(model, active=tuple(b for b in model.active if b is not a))
            refined = self.fitter.refine(rest, a.candidate, a.params, model.fit.structure, model.delay_free)
            active = dict(refined.active)
            if "delay" in model.by_slot():
                active["delay"] = model.by_slot()["delay"]
            new = self.scorer.model(active, refined.fit, model.delay_free, refined.flow, target=aim.y)
            if new.bic < model.bic:
                model = new
        return model
