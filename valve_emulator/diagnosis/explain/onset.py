r"""Physics that starts part-way through a record: when it starts, and its fit on the part where it acts.

A valve can start to stick in the middle of a long record. Fitted over the whole record, a stiction valve
must also explain the healthy part, where the valve followed OP: the fit settles on a smaller band, and what
it leaves over is taken up by physics that is not there (a dead-time error, a characteristic). So for every
candidate that :attr:`~valve_emulator.diagnosis.candidates.base.ChainCandidate.may_start_late`, the search
also fits it as :class:`LateOnset`: the slot passes its signal
through before an onset time ``t0`` and the candidate acts from ``t0`` on, its state started there.

Locating the onset before the fit (:func:`suspect_onset`)
--------------------------------------------------------
A valve that starts to stick makes a healthy loop cycle from then on: the energy of the control error
``SP − PV`` steps up. The record is cut into :data:`BLOCKS` blocks, and the least-squares step in the mean
of their log energies is the change point; it is *suspected* when the energy rises by :data:`MIN_RISE` (in
log) and the step explains :data:`MIN_SHARE` of the variance (without a set point, PV's fast part stands in:
PV less its moving mean over a tenth of the record or two of its cycles, whichever is longer).
Where one is suspected so late that the usual split (the last 30 % held out) would leave less than
:data:`MIN_ACTING` of the record after it to fit, with a model (``"split"`` validation) the held-out part is
the last 30 % of the part after it (:func:`post_onset_split`): a valve that starts to stick after 60 % of the
record would otherwise act mostly where it is never fitted.

Fitting the onset (:func:`onset_option`)
---------------------------------------
With a suspected onset the fit is tried with and without a model. Without one it is tried only with a model
and where the residual says the physics may start late: the whole-record option's improvement lies mostly in
the second half of the fit part (:data:`EARLY_SHARE`). Then:

1. **coarse**: the candidate's coarse grid at each onset :data:`NEAR` the suspected one (else at each of
   :data:`ONSETS` fractions of the fit part), scored at the poles of the model being extended, of the
   candidate's own whole-record option and, with a model, at the nominal linear part (the onset and the band
   trade off: a coarse grid over both, not a line search from the whole-record fit; around a linear part
   whose gain leans on a wandering load the best late band is too small to count);
2. **scan**: the candidate's global scan (fine in S for stiction) at the best onset;
3. **refine**: the fitter's refinement of the candidate's parameters, its fine grid also moving the onset
   by :attr:`LateOnset.onset_step` of the record (twice), the
   threshold parameters centred. A late band below :data:`MIN_BAND` of the OP span is no onset (see
   :func:`_material`).

An onset before the fit part (which starts after every candidate's burn-in, up to a third of the record)
cannot be told by the fit from one a little earlier: there the located one stands, give or take the
refinement's steps, and the band is fitted on the part where it acts. An onset that leaves less than
:data:`MIN_BEFORE` of the record between where the linear part has settled and itself cannot be told from
one at the start at all: the search withdraws it (:meth:`~valve_emulator.diagnosis.explain.search.Search.
shows_onset`).

Why only with a model where no onset is suspected: without one the linear part is identified from the same
record, and a band acting late at any of the coarse onsets trades off against it (on the shared plant windows
it named a healthy level valve sticky, where the whole-record search did not).

Where an onset was suspected the fit is also made under the drifting-load noise model
(:func:`late_options`): the grids scored through that model's prefilter, the linear part fitted again in
the search's domain afterwards.

The search (:mod:`~valve_emulator.diagnosis.explain.search`) offers the late options beside the whole-record
ones. Where an onset was suspected, a late option counts against the model being extended by the significance
rule or by a BIC 10 lower under the drifting-load noise model; of the late options that count, the fit of each
physics with the better held-out fit stands for it and the physics with the lowest BIC leads; every other
option stays only if it beats that one, significant against it and 10 lower in BIC under the drifting-load
noise model too (:meth:`~valve_emulator.diagnosis.explain.search.Search.late_first`): before a valve starts to
stick the controller moves OP to cancel a wandering load while PV holds its set point, so in the search's
free-run cost a valve stuck there — or a linear part whose gain shrinks — fits that part *better* than the
healthy one, and the free run alone cannot ask for the onset. Where none was, the late option replaces the
whole-record one when it lowers BIC by twice the search's own threshold (the onset is then a change point, the
best of many positions; preferring it whenever the whole-record one was not better by the threshold located
wrong onsets as often as right ones). Once a finding starts late, later additions must also lower the BIC of
the part after the onset (:func:`bic_after`) and the BIC under the drifting-load noise model, and fit the
healthy part before it no worse (:func:`before_part`): only the valve starts late, what is added beside it
belongs to the loop throughout.

What the answer says (:func:`acting_part`): the onset, and the fits (%) of the model without the finding and of
the final model on the samples from the onset on, so that the finding is judged where it acts and is not
credited with the healthy part.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainCandidate, ChainContext
from valve_emulator.diagnosis.explain.locate import turning_points
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.closed_loop import Identification, setpoint_moves
from valve_emulator.diagnosis.fit.cost import ar1_bic
from valve_emulator.diagnosis.fit.data import HELD_OUT, Problem, fit_percent
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.linear import highpass
from valve_emulator.diagnosis.fit.load_check import load_bic
from valve_emulator.diagnosis.fit.nominal import identify_before
from valve_emulator.diagnosis.fit.records import Model, Option
from valve_emulator.diagnosis.fit.scorer import Scorer, sse_jobs_shared

__all__ = ["ONSETS", "EARLY_SHARE", "MIN_BAND", "BLOCKS", "MIN_RISE", "MIN_SHARE", "MIN_ACTING", "NEAR", "LateOnset",
           "Onset", "Suspected", "suspect_onset", "post_onset_split", "onset_option", "acting_part", "onset_of",
           "late_start", "bic_after", "before_part", "bic_on", "late_options", "MIN_BEFORE", "FAR_DELAY",
           "delay_cap", "far_beyond", "throughout"]

#: Onsets of the coarse stage, as fractions of the fit part: the physics acts on a quarter of it at least, so
#: that a short stretch near the end (a few cycles of a load the linear part misses) is not fitted as a valve
#: that began to stick there.
ONSETS = tuple(np.round(np.linspace(0.1, 0.75, 14), 3))
#: The onset is searched only when the whole-record option's improvement of the residual lies less than this
#: share in the first half of the fit part (:func:`_early_share`; uniform physics puts about half there).
EARLY_SHARE = 0.4
#: Least band (first OP-sized parameter) of a late fit, as a fraction of the OP span (see :func:`_material`).
MIN_BAND = 0.05
#: Blocks the record is cut into to locate a change in the control error's energy (:func:`suspect_onset`).
BLOCKS = 100
#: Least rise of the mean log block energy at a suspected onset (e: the energy grows about 2.7-fold).
MIN_RISE = 1.0
#: Least share of the log block energy's variance that the two-segment step explains.
MIN_SHARE = 0.15
#: Least part of the record (fraction) after a suspected onset that the usual split must leave in the fit part;
#: with less, the held-out part moves after the onset (:func:`post_onset_split`).
MIN_ACTING = 0.1
#: Least part of the record (fraction) in the fit part before a late finding's onset on which an addition beside
#: it is also judged (:func:`before_part`).
MIN_BEFORE = 0.1
#: Without a model, a dead time longer than this times the healthy part's (plus as many samples) is the sticky
#: cycle's shift, not the plant's (:func:`delay_cap`).
FAR_DELAY = 2.0
#: Onsets a located change point lets the fit try, as fractions of the record around it.
NEAR = tuple(np.round(np.linspace(-0.06, 0.06, 7), 3))


class LateOnset(ChainCandidate):
    """A chain candidate that acts only from an onset time on: before it its slot passes the signal through, as
    a healthy element does; from it on the candidate acts, its state started afresh at the onset sample.

    Its parameter vector is the inner candidate's followed by ``onset`` (s from the record's first sample),
    counted by BIC; its name, slot, units and twin role are the inner candidate's, so a finding of it is the
    inner physics with ``onset_s`` among its parameters. Its grids are the inner candidate's at a given onset
    (the onset is searched by :func:`onset_option`); its refinement also moves the
    onset, by :attr:`onset_step` times the record's length.
    """

    #: The onset refinement's step, as a fraction of the record's length (±4 steps around the best).
    onset_step: ClassVar[float] = 1.0 / 160.0

    def __init__(self, inner: ChainCandidate) -> None:
        self.inner = inner
        self.name = inner.name
        self.slot = inner.slot
        self.param_names = (*inner.param_names, "onset")
        self.n_params = inner.n_params + 1
        self.dims = inner.dims
        self.cause_rank = inner.cause_rank
        self.needs_span = inner.needs_span
        self.twin_role = inner.twin_role
        self.threshold_axes = inner.threshold_axes

    @staticmethod
    def with_onset(rows: np.ndarray, onset: float | np.ndarray) -> np.ndarray:
        """The inner candidate's parameter rows with an onset column (one value, or one per row)."""
        rows = np.atleast_2d(rows)
        return np.column_stack([rows, np.broadcast_to(np.asarray(onset, dtype=float), (rows.shape[0],))])

    def _at(self, rows: np.ndarray, best: np.ndarray) -> np.ndarray:
        return self.with_onset(rows, best[-1])

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return self.with_onset(self.inner.grid(ctx), 0.0)

    def scan(self, ctx: ChainContext) -> np.ndarray | None:
        rows = self.inner.scan(ctx)
        return None if rows is None else self.with_onset(rows, 0.0)

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        h = self.onset_step * ctx.op.size * ctx.dt
        onsets = best[-1] + h * np.arange(-4, 5)
        along = self.with_onset(np.repeat(best[None, :-1], onsets.size, axis=0), onsets)
        return np.vstack([self._at(self.inner.refine(ctx, best[:-1]), best), along[along[:, -1] >= 0.0]])

    def profile_grid(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        return self._at(self.inner.profile_grid(ctx, best[:-1]), best)

    def line(self, ctx: ChainContext, best: np.ndarray, axis: int) -> np.ndarray:
        return self._at(self.inner.line(ctx, best[:-1], axis), best)

    def burn_in(self, ctx: ChainContext) -> int:
        return self.inner.burn_in(ctx)

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        T, n = x.shape[0], params.shape[0]
        starts = np.clip(np.round(params[:, -1] / ctx.dt).astype(np.int64), 0, T)
        out = np.empty((T, n))
        for k0 in np.unique(starts):
            rows = _as_slice(np.flatnonzero(starts == k0))
            xs = x if x.ndim == 1 else np.ascontiguousarray(x[:, rows])
            acts = T - k0 >= 2   # the inner candidate acts from the onset sample on, started there
            until = k0 if acts else T
            out[:until, rows] = xs[:until, None] if x.ndim == 1 else xs[:until]
            if acts:
                out[k0:, rows] = self.inner.apply(xs[k0:], params[rows, :-1], ctx)
        return out

    def parameters(self, p: np.ndarray) -> dict:
        return {**self.inner.parameters(p[:-1]), "onset_s": round(float(p[-1]), 1)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"{self.inner.describe(p[:-1], nominal, units, edges)}, from t ≈ {p[-1]:.4g} s on"

    def bounds(self, ctx: ChainContext) -> dict[str, tuple[float | None, float | None]]:
        return self.inner.bounds(ctx)  # the onset runs over the record, whose ends are no edge of the physics


def _as_slice(rows: np.ndarray) -> slice | np.ndarray:
    """Sorted row indices as a slice when they are one contiguous run (the usual case: a grid's rows at one
    onset), whose columns numpy copies in blocks instead of one index at a time."""
    if rows.size and rows[-1] - rows[0] + 1 == rows.size:
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


@dataclass(frozen=True)
class Onset:
    """When a finding starts and how the model fits where it acts.

    Attributes
    ----------
    onset_s : time from the record's first sample (s).
    fit_before : free-run fit (%) from the onset on of the model the diagnosis started from.
    fit_after : the same of the final model.
    """

    onset_s: float
    fit_before: float
    fit_after: float

    def sentence(self) -> str:
        """One line for the report: when, and the fits where the finding acts."""
        return (f"from t ≈ {self.onset_s:.4g} s on; free-run fit from then on {self.fit_before:.1f} % without the "
                f"finding, {self.fit_after:.1f} % with it")

    def to_json(self) -> dict:
        return {"onset_s": round(self.onset_s, 1), "fit_before": round(self.fit_before, 2),
                "fit_after": round(self.fit_after, 2)}


@dataclass(frozen=True)
class Suspected:
    """A step up in the energy of the loop's control error, located before any fit (:func:`suspect_onset`).

    Attributes
    ----------
    sample : first sample after the step.
    rise : mean log block energy after the step minus before it (1 is an energy about 2.7 times larger).
    share : share of the log block energies' variance that the step explains.
    signal : the signal whose energy stepped: ``"SP − PV"``, or ``"PV"`` (its fast part) without a set point.
    """

    sample: int
    rise: float
    share: float
    signal: str


def _log_blocks(e: np.ndarray, n_blocks: int) -> tuple[np.ndarray, int]:
    """Log of the mean of ``e`` over consecutive blocks, and the block length (samples)."""
    w = max(1, e.size // n_blocks)
    n = e.size // w
    floor = 1e-12 * float(np.mean(e)) + 1e-300
    return np.log(e[:n * w].reshape(n, w).mean(axis=1) + floor), w


def _step_in_mean(b: np.ndarray, lo: int, hi: int) -> tuple[int, float, float]:
    """The least-squares two-segment step of ``b`` with its first block in ``[lo, hi)``: where, how high, and
    the share of ``b``'s variance it explains."""
    c, c2 = np.cumsum(b), np.cumsum(b * b)
    n = b.size
    k = np.arange(lo, hi)
    m1, m2 = c[k - 1] / k, (c[-1] - c[k - 1]) / (n - k)
    sse = c2[-1] - k * m1 ** 2 - (n - k) * m2 ** 2
    sse0 = c2[-1] - c[-1] ** 2 / n
    i = int(np.argmin(sse))
    return int(k[i]), float(m2[i] - m1[i]), float(1.0 - sse[i] / sse0) if sse0 > 0 else 0.0


def _moving_mean(x: np.ndarray, w: int) -> np.ndarray:
    c = np.concatenate([[0.0], np.cumsum(x, dtype=float)])
    idx = np.arange(x.size)
    lo, hi = np.clip(idx - w // 2, 0, x.size), np.clip(idx - w // 2 + w, 0, x.size)
    return (c[hi] - c[lo]) / np.maximum(hi - lo, 1)


def _cycle_period(x: np.ndarray) -> float | None:
    """Period (samples) of ``x``'s largest swings: twice the median spacing of its turning points with a
    hysteresis of half its 5–95 % range; None with fewer than three turns."""
    lo, hi = np.percentile(x, [5.0, 95.0])
    turns = turning_points(x, 0.5 * float(hi - lo))
    return 2.0 * float(np.median(np.diff(turns))) if turns.size >= 3 else None


def _fast_part(pv: np.ndarray) -> np.ndarray:
    """PV less its moving mean over a tenth of the record, or over two of PV's cycles where those are longer
    (at most half the record).

    Over a window shorter than the loop's cycle the moving mean follows PV through a long dwell, and the
    fast part falls to the noise there: a sticky loop's first, slower cycle (a valve that rests longer before
    it first slips) then reads as a quiet stretch before a change (the proof cases' concentration loop at
    1,000 samples, a cycle of about 230 s against a window of 100, was answered as sticking from t ≈ 210 s
    on)."""
    w = max(1, pv.size // 10)
    period = _cycle_period(pv)
    if period is not None:
        w = max(w, min(int(round(2.0 * period)), pv.size // 2))
    return pv - _moving_mean(pv, w)


def suspect_onset(pv: np.ndarray, sp: np.ndarray | None = None, *, start: int = 0) -> Suspected | None:
    """Where a loop's control error steps up for good, if it does: a valve that starts to stick part-way
    makes a healthy loop cycle from then on.

    The squared control error ``(SP − PV)²`` (without a set point: PV's fast part, :func:`_fast_part`)
    is averaged over :data:`BLOCKS` blocks; the least-squares step in the mean of their logs (the log keeps
    one set-point response from weighing like a lasting cycle) is the change point. It counts when the
    energy rises by :data:`MIN_RISE` at least and the step explains :data:`MIN_SHARE` of the variance, away
    from the searched span's ends: a step at the first possible block is a change before it (before the
    first set-point move a loop is quiet whether its valve sticks or not), so the search starts after
    ``start`` and two blocks after the set point first moves.

    Measured on the independent simulator's ``late_onset`` loops (onset drawn in the middle 60 % of the
    record): within 10 % of the record in 22 of 24 draws. None when no step counts.
    """
    pv = np.asarray(pv, dtype=float)
    has_sp = sp is not None and bool(np.all(np.isfinite(sp)))
    if has_sp:
        e, signal = (np.asarray(sp, dtype=float) - pv) ** 2, "SP − PV"
    else:
        e, signal = _fast_part(pv) ** 2, "PV"
    b, w = _log_blocks(e, BLOCKS)
    first = start
    if has_sp:
        moves = setpoint_moves(sp)
        first = max(first, int(moves[0]) if moves.size else 0)
    lo, hi = max(int(np.ceil(first / w)) + 2, b.size // 20, 2), b.size - b.size // 20
    if hi - lo < 6:
        return None
    k, rise, share = _step_in_mean(b, lo, hi)
    if k <= lo + 1 or k >= hi - 2 or rise < MIN_RISE or share < MIN_SHARE:
        return None
    return Suspected(sample=k * w, rise=rise, share=share, signal=signal)


def delay_cap(problem: Problem, sp: np.ndarray | None, delay: float,
              constraints: Identification | None) -> float | None:
    """Without a model: the longest dead time (s) the search may give the plant where a change point is
    located and the dead time it found (``delay``) is more than :data:`FAR_DELAY` times the healthy part's
    plus as many samples — the healthy part's dead time and a sample; None otherwise.

    The healthy part's dead time: the plant identified before the change point, where the valve is still
    healthy and the loop linear, from OP's part that the set point drives
    (:func:`~valve_emulator.diagnosis.fit.nominal.identify_before`: the two-stage method; None where the set
    point moves fewer than twice there). Not where the set point moves within a block of the change point
    (:data:`BLOCKS`): the step in the control error's energy may then be that move's answer, and the part
    before it not a healthy loop (a plant window labelled sticky throughout, 751 samples, its change point 3
    samples before a set-point move near its end, was capped at one sample of dead time and answered
    ``no_stiction``). Why: a linear OP → PV relation fitted over a sticky limit cycle takes
    up the shift between OP's triangle and PV's cycle in its dead time, and a wandering load biases the fit
    from OP itself. On the independent ``late_onset`` loops as plant data, the search's dead time was 17–35 s
    for 0.3–7 s behind a lag (draws 0, 3, 5, 10 of the onset property) and the band fitted around it 46–91 %
    off; before the change point the two-stage dead time lies within the loop's dead time and lag (and 5 s) in
    10 of the 13 draws where it speaks. Capping every search there (at 1–1.5 times the healthy dead time, plus
    1–3 samples) traded J against the dead time on draws whose dead time was already near (one or two draws
    that held lost J), so the cap acts only where the dead time is far from the healthy part's: on draws 0 and
    3, of which draw 0 now holds (``docs/diagnosis.md``, *Physics that starts part-way*)."""
    suspected = suspect_onset(problem.pv, sp)
    if suspected is None or _at_setpoint_move(sp, suspected.sample, problem.T // BLOCKS):
        return None
    healthy = identify_before(problem, sp, suspected.sample, constraints=constraints)
    if healthy is None or not far_beyond(delay, healthy.delay, problem.dt):
        return None
    return healthy.delay + problem.dt


def far_beyond(delay: float, bound: float, dt: float) -> bool:
    """Whether a dead time a search found (``delay``, s) is more than :data:`FAR_DELAY` times ``bound`` (s, a
    dead time the loop is shown to have at most) plus as many samples of ``dt`` s: the sticky cycle's shift,
    where a plant's lag taken up into its dead time stays nearer."""
    return delay > FAR_DELAY * bound + FAR_DELAY * dt


def _at_setpoint_move(sp: np.ndarray | None, sample: int, width: int) -> bool:
    """Whether the set point moves within ``width`` samples of ``sample`` (False without a set point)."""
    if sp is None:
        return False
    return bool(np.any(np.abs(setpoint_moves(sp) - sample) <= width))


def post_onset_split(problem: Problem, suspected: Suspected | None) -> Problem:
    """``problem`` with its held-out part the last :data:`~valve_emulator.diagnosis.fit.data.HELD_OUT` of the
    part after a suspected onset, where the usual split would leave less than :data:`MIN_ACTING` of the record
    after the onset to fit (``"split"`` validation only): held out from the record's end, a valve that starts
    to stick late acts mostly in the held-out part and is hardly fitted. (Measured on the independent
    ``late_onset`` loops: for earlier onsets the usual split fits the band as well or better, and a longer
    fit part made one clear-cut loop's late fit settle on a wrong slip jump.)"""
    if suspected is None or problem.validation != "split":
        return problem
    w0, w1 = problem.train
    if w1 - suspected.sample >= MIN_ACTING * problem.T:
        return problem
    after = suspected.sample + int(round((1.0 - HELD_OUT) * (problem.T - suspected.sample)))
    return replace(problem, train=(w0, after)) if after > w1 else problem


def _onsets(problem: Problem, suspected: Suspected | None) -> np.ndarray:
    """Onsets (s) of the coarse stage: :data:`ONSETS` of the fit part, or :data:`NEAR` a located change point,
    the nearest first (an onset before the fit part scores about alike wherever it is: the first best stands),
    up to the last tenth of the fit part."""
    w0, w1 = problem.train
    if suspected is None:
        return (w0 + np.asarray(ONSETS) * (w1 - w0)) * problem.dt
    near = np.asarray(NEAR)
    k = np.round(suspected.sample + near[np.argsort(np.abs(near), kind="stable")] * problem.T)
    return k[(k >= 1) & (k <= w1 - 0.1 * (w1 - w0))] * problem.dt


def _coarse_rows(fitter: Fitter, cand: ChainCandidate, ctx, suspected: Suspected | None) -> np.ndarray:
    """The candidate's coarse grid at every onset of :func:`_onsets`."""
    inner = cand.grid(ctx)
    rows = [LateOnset.with_onset(inner, t0) for t0 in _onsets(fitter.p, suspected)]
    return np.vstack(rows) if rows else np.empty((0, inner.shape[1] + 1))


def _early_share(problem: Problem, without: Model, plain: Model) -> float:
    """Share of the whole-record option's improvement of the squared residual that lies in the first half of
    the fit part (a change point in the residual: physics acting from the start improves both halves alike)."""
    w0, w1 = problem.train
    gain = ((problem.y - without.y_hat) ** 2 - (problem.y - plain.y_hat) ** 2)[w0:w1]
    total = float(gain.sum())
    return 1.0 if total <= 0.0 else float(gain[:gain.size // 2].sum()) / total


def _material(cand: ChainCandidate, params: np.ndarray, op_span: float) -> bool:
    """Whether the late fit's first OP-sized parameter (a valve's band) is at least :data:`MIN_BAND` of the OP
    span: a tiny band with a larger jump, acting late, walks with OP's noise and fits a slow drift near the end
    of a record, not a valve that began to stick there."""
    sized = [i for i, name in enumerate(cand.param_names) if cand.dims.get(name) == "op"]
    return not sized or params[sized[0]] >= MIN_BAND * op_span


def _lateable(cand: Candidate, plain: Option) -> bool:
    """Whether ``cand`` may start late and ``plain`` adds it alone (not with a freed dead time)."""
    return getattr(cand, "may_start_late", False) and plain.added == (cand.name,)


def onset_option(fitter: Fitter, model: Model, cand: Candidate, plain: Option) -> Option | None:
    """``cand`` added to ``model`` acting from an onset fitted over the record, where none was located before
    the search (see the module docstring; at a located onset: :func:`late_options`); None for a candidate that
    cannot start late or an option that frees the dead time with it, without a nominal model, or when the
    whole-record option's gain is not mostly late."""
    if not _lateable(cand, plain):
        return None
    if not fitter.nominal.given or _early_share(fitter.p, model, plain.model) >= EARLY_SHARE:
        return None
    return _late_fits([fitter], fitter, model, cand, plain, None)[0]


def late_options(fitter: Fitter, model: Model, cand: Candidate, plain: Option,
                 suspected: Suspected) -> tuple[Option | None, Option | None]:
    """The late option of ``cand`` at a located onset (``suspected``), fitted twice: in the search's own domain,
    and with the late valve's parameters fitted under the drifting-load noise model
    (:mod:`~valve_emulator.diagnosis.fit.load_check`) — the grids scored on PV and the chain's output through
    the prefilter of that model at the λ that suits ``model`` best, then the linear part fitted again in the
    search's own domain. ``(late, through the noise model)``; each None where :func:`onset_option` gives None.

    Why the second fit: before the onset the controller cancels a wandering load with OP while PV holds its set
    point, and the free run replays those moves into PV swings that never happened. Around the linear part it
    fits, the free run's best late valve is then a band too small to count (it stays close to the healthy valve
    that replays least): on the independent ``late_onset`` loops with their model, a valve of S = 3.4 % from
    t = 634 s was fitted with a band below a twentieth of OP's span. Through the noise model's prefilter the
    load is forgotten within its time scale, and the band is fitted to the cycles the valve makes.

    The two fits differ only in the cost domain of their grids, so they are searched side by side: the coarse
    rows go through the chain once for both, and the scan too where both coarse stages chose the same onset."""
    if not _lateable(cand, plain):
        return None, None
    late, through = _late_fits([fitter, _through_load(fitter, model)], fitter, model, cand, plain, suspected)
    return late, through


def _through_load(fitter: Fitter, model: Model) -> Fitter:
    """A fitter of ``fitter``'s problem in the cost domain of the drifting-load noise model that suits ``model``
    best (its prefilter at that λ)."""
    lam = load_bic(fitter.scorer, model)[1]
    scorer = fitter.scorer
    return Fitter(Scorer(replace(fitter.p, prefilter=lam), scorer.nominal, scorer.library))


def _structures(fitter: Fitter, model: Model, plain: Option) -> list:
    """Linear parts the coarse stage of a late fit tries: the model's, the whole-record option's and, with a
    nominal model, the nominal one at the model's dead time."""
    out = [model.fit.structure, plain.model.fit.structure]
    if fitter.nominal.given:
        out.append(replace(fitter.nominal.structure, delay=model.fit.structure.delay))
    return list({id(s): s for s in out}.values())


def _late_fits(searchers: list[Fitter], fitter: Fitter, model: Model, cand: ChainCandidate, plain: Option,
               suspected: Suspected | None) -> list[Option | None]:
    """The late option of ``cand`` searched by each of ``searchers`` (coarse, scan, refine; module docstring) and
    scored by ``fitter`` (the search's own: where a searcher differs, the linear part is fitted again in its
    domain).

    The searchers differ only in their cost domain (:func:`~valve_emulator.diagnosis.fit.scorer.
    sse_jobs_shared`): each chunk of the coarse rows leaves the chain once and is scored for every searcher and
    each of its linear structures, and so is the scan's for searchers whose coarse stages chose the same onset —
    the numbers of a search of its own."""
    late = LateOnset(cand)
    ctx = searchers[0].scorer.ctx(model)
    active = model.by_slot()
    rows = _coarse_rows(searchers[0], cand, ctx, suspected)
    if rows.size == 0:
        return [None] * len(searchers)
    aims = [s.scorer.aim(model) for s in searchers]
    structures = [_structures(s, model, plain) for s in searchers]
    coarse = sse_jobs_shared(active, ctx, late, rows, [(s.scorer, [(st, None) for st in sts], aim)
                                                       for s, sts, aim in zip(searchers, structures, aims)])
    starts = []
    for sts, scored in zip(structures, coarse):
        best = None
        for st, (sse, _) in zip(sts, scored):
            i = int(np.argmin(sse[:, 0]))
            if best is None or sse[i, 0] < best[0]:
                best = (float(sse[i, 0]), rows[i], st)
        starts.append(best[1:])
    scans = _late_scans(searchers, aims, active, ctx, late, cand.scan(ctx), starts)
    out = []
    for searching, (row, st), scanned in zip(searchers, starts, scans):
        scan_surface = None
        if scanned is not None:
            scan, sse = scanned
            row = scan[int(np.argmin(sse))]
            scan_surface = replace(fitter.surface(cand.name, scan, sse), load_model=searching is not fitter)
        out.append(_late_refined(searching, fitter, model, late, row, st, ctx, scan_surface))
    return out


def _late_scans(searchers: list[Fitter], aims: list, active, ctx, late: LateOnset, scan: np.ndarray | None,
                starts: list[tuple]) -> list[tuple | None]:
    """Per searcher, the candidate's scan at the onset of its coarse start and the SSE of each row at the
    start's linear structure (None without a scan); searchers at one onset share the chain's pass."""
    out: list[tuple | None] = [None] * len(searchers)
    if scan is None:
        return out
    at: dict[float, list[int]] = {}
    for k, (row, _) in enumerate(starts):
        at.setdefault(float(row[-1]), []).append(k)
    for ks in at.values():
        rows = LateOnset.with_onset(scan, starts[ks[0]][0][-1])
        scored = sse_jobs_shared(active, ctx, late, rows, [(searchers[k].scorer, [(starts[k][1], None)], aims[k])
                                                          for k in ks])
        for k, [(sse, _)] in zip(ks, scored):
            out[k] = (rows, sse[:, 0])
    return out


def _late_refined(searching: Fitter, fitter: Fitter, model: Model, late: LateOnset, row: np.ndarray,
                  st, ctx: ChainContext, scan_surface) -> Option | None:
    """The late option refined by ``searching`` from ``row`` at ``st`` and scored by ``fitter``; None when its band
    is not material (:func:`_material`)."""
    cand = late.inner
    r = searching.refine(model, late, row, st, model.delay_free, joint=False)
    if not _material(cand, r.active[cand.slot].params, ctx.op_span):
        return None
    own = fitter.scorer
    target = own.aim(model)
    fit = r.fit if searching is fitter else own.polish(r.flow, r.fit.structure, model.delay_free, target)
    m = own.model(r.active, fit, model.delay_free, r.flow, target=target.y)
    return Option(added=(cand.name,), model=m, coarse=None, scan=scan_surface, fine=r.fine)


def onset_of(model: Model, name: str) -> float | None:
    """The onset (s) of finding ``name`` in ``model``, None when it acts from the start."""
    act = next((a for a in model.active if a.name == name), None)
    if act is None or not isinstance(act.candidate, LateOnset):
        return None
    return float(act.params[-1])


def late_start(model: Model) -> float | None:
    """The onset (s) of the earliest finding of ``model`` that starts late, None when none does."""
    onsets = [float(a.params[-1]) for a in model.active if isinstance(a.candidate, LateOnset)]
    return min(onsets) if onsets else None


def throughout(scorer: Scorer, model: Model) -> Model:
    """``model`` with every finding that starts late acting from the record's first sample instead, its state
    started there (the same parameters), and the linear part polished again from ``model``'s: the valve that
    would stick throughout, against which the part before an onset must show a healthy valve
    (:meth:`~valve_emulator.diagnosis.explain.search.Search.healthy_before`)."""
    active = {a.slot: Active(a.candidate.inner, np.asarray(a.params[:-1])) if isinstance(a.candidate, LateOnset)
              else a for a in model.active}
    flow = scorer.chain(active, scorer.ctx(model))[:, 0]
    aim = scorer.aim(model)
    fit = scorer.polish(flow, model.fit.structure, model.delay_free, aim)
    return scorer.model(active, fit, model.delay_free, flow, target=aim.y)


def bic_after(problem: Problem, model: Model, start: int) -> float:
    """BIC of ``model`` on its fit part from sample ``start`` on, under an AR(1) error (the residual of the
    linear part against what it was fitted to, in the search's domain, as the search's two-fold BIC).

    Where a finding starts late the record holds two regimes, and physics added after it must hold where it
    acts: a dead time, a load or a characteristic that only mends the part before the onset (where a
    wandering load the model leaves out dominates the free-run residual) is not a finding of the loop the
    valve now runs in."""
    w0, w1 = problem.train
    return bic_on(problem, model, (max(w0, start), w1))


def before_part(problem: Problem, start: int, *models: Model) -> tuple[int, int] | None:
    """The samples before onset sample ``start`` on which ``models`` are judged (:func:`bic_on`): from where the
    linear part of each has settled from its unknown initial state — its dead time and five of its longest time
    constants, or the fit part's start where that is earlier — up to the onset (at most the fit part's end).
    None when that part is shorter than :data:`MIN_BEFORE` of the record.

    Why from where the linear part has settled and not from the fit part's start: the fit part starts after
    the valve candidates' burn-in, which on a loop whose OP moves little at first (a healthy valve under a
    wandering load) takes up to a third of the record, so a valve that starts to stick at a fifth to two
    fifths of the record would leave nothing before its onset to judge by; a valve that starts late is
    healthy there and has no state to forget."""
    w0, w1 = problem.train
    settle = max(_settle_samples(problem.dt, m.fit.structure) for m in models)
    window = (min(w0, settle), min(start, w1))
    return window if window[1] - window[0] >= MIN_BEFORE * problem.T else None


def _settle_samples(dt: float, structure) -> int:
    """Samples a linear part takes to forget its initial state: its dead time and five times its slowest time
    constant (real poles and the nominal model's fixed ones), plus the four samples the data's burn-in adds to a
    dead time (:func:`~valve_emulator.diagnosis.fit.data.prepare`; its settling time is four time constants)."""
    taus = [*structure.taus, *(1.0 / abs(p.real) for p in structure.fixed_poles if p.real != 0.0)]
    return int(np.ceil((structure.delay + 5.0 * max(taus, default=0.0)) / dt)) + 4


def bic_on(problem: Problem, model: Model, window: tuple[int, int]) -> float:
    """BIC of ``model``'s residual (against what its linear part was fitted to, in the search's domain) on the
    samples of ``window`` under an AR(1) error."""
    target = problem.y if model.target is None else model.target
    r = target - model.fit.predict(model.flow, problem.dt)
    if problem.prefilter is not None:
        r = highpass(r, problem.prefilter)
    return ar1_bic(r[window[0]:window[1]], model.k)


def acting_part(problem: Problem, model: Model, pv_before: np.ndarray, findings: tuple) -> tuple:
    """``findings`` with the :class:`Onset` of each that starts late: its onset and the fits from it on of the
    model the diagnosis started from (``pv_before``) and of the final ``model``."""
    out = []
    pv_after = problem.to_pv(model.y_hat)
    for f in findings:
        t0 = onset_of(model, f.physics)
        if t0 is not None:
            k0 = min(int(round(t0 / problem.dt)), problem.T - 2)
            f = replace(f, onset=Onset(onset_s=t0, fit_before=fit_percent(problem.pv[k0:], pv_before[k0:]),
                                       fit_after=fit_percent(problem.pv[k0:], pv_after[k0:])))
        out.append(f)
    return tuple(out)


def late_afresh(fitter: Fitter, model: Model) -> Model:
    """``model`` with its finding that starts late searched again at its onset: the candidate's coarse grid
    scored around the rest of ``model`` (its linear part as it stands), then refined from the best row (the
    onset refined with it); kept where it lowers the BIC under both noise models (the search's, and the
    drifting-load one of :mod:`~valve_emulator.diagnosis.fit.load_check`), else ``model``, which is also the
    answer where no finding starts late.

    Why: a late valve refined again after the linear part moved (the nominal gain held, :mod:`~valve_emulator.
    diagnosis.explain.prior`) starts from the band that suited the other gain, and a band is a basin of its own:
    on the independent ``late_onset`` loops with their model (draw 10 of the onset property, a Karnopp stem of
    S 4.33 % on a level loop), refined from S 2.39 % around the nominal gain it stayed at 2.58 %; searched
    afresh it is 4.03 % (BIC 1,269 lower, 198 lower under the drifting-load noise model). Why both noise
    models: the free run's cost also rewards a valve that replays the controller's answers to a wandering load
    away (*Where an onset is located*, docs/diagnosis.md); on draw 6 the fresh search's band (S 2.62 % for
    3.38, its onset 0.11 of the record late) was 734 lower in the search's BIC and 40 *higher* under the load's
    noise model, and it is not kept."""
    a = next((a for a in model.active if isinstance(a.candidate, LateOnset)), None)
    if a is None:
        return model
    scorer = fitter.scorer
    rest = replace(model, active=tuple(b for b in model.active if b is not a))
    ctx, aim, st = scorer.ctx(model), scorer.aim(model), model.fit.structure
    rows = LateOnset.with_onset(a.candidate.inner.grid(ctx), float(a.params[-1]))
    sse, _ = scorer.sse_grid(rest.by_slot(), ctx, a.candidate, rows, st, None, aim)
    r = fitter.refine(rest, a.candidate, rows[int(np.argmin(sse[:, 0]))], st, model.delay_free)
    active = dict(r.active)
    if "delay" in model.by_slot():
        active["delay"] = model.by_slot()["delay"]
    new = scorer.model(active, r.fit, model.delay_free, r.flow, target=aim.y)
    better = new.bic < model.bic and load_bic(scorer, new)[0] < load_bic(scorer, model)[0]
    return new if better else model
