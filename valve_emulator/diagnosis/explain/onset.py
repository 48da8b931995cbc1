r"""Physics that starts part-way through a record: when it starts, and its fit on the part where it acts.

A valve can start to stick in the middle of a long record. Fitted over the whole record, a stiction valve
must also explain the healthy part, where the valve followed OP: the fit settles on a smaller band, and what
it leaves over is taken up by physics that is not there (a dead-time error, a characteristic). So for every
candidate that :attr:`~valve_emulator.diagnosis.candidates.base.ChainCandidate.may_start_late`, the search
also fits it as :class:`LateOnset`: the slot passes its signal
through before an onset time ``t0`` and the candidate acts from ``t0`` on, its state started there.

Fitting the onset (:func:`onset_option`)
---------------------------------------
It is fitted only where the residual says the physics may start late: the whole-record option's
improvement lies mostly in the second half of the fit part (:data:`EARLY_SHARE`). Then:

1. **coarse**: the candidate's coarse grid at each onset of :data:`ONSETS` fractions of the fit part, scored
   at the poles of the model being extended and of the candidate's own whole-record option (the onset and
   the band trade off: a coarse grid over both, not a line search from the whole-record fit);
2. **scan**: the candidate's global scan (fine in S for stiction) at the best onset;
3. **refine**: the fitter's refinement of the candidate's parameters, its fine grid also moving the onset
   by :attr:`LateOnset.onset_step` of the record (twice), the
   threshold parameters centred. A late band below :data:`MIN_BAND` of the OP span is no onset (see
   :func:`_material`).

Only with a nominal model: without one the linear part is identified from the same record, and a band acting
late trades off against it (on the shared plant windows it named a healthy level valve sticky, where the
whole-record search did not).

The search (:mod:`~valve_emulator.diagnosis.explain.search`) offers the late option in place of the
whole-record one when it lowers BIC by twice the search's own threshold: the onset is a change point, the
best of many positions. (Measured on
the independent ``late_onset`` loops: before a valve starts to stick the loop's OP moves little, and a sticky
valve fits that part about as well as a healthy one, so BIC often cannot ask for the onset; preferring the
late option whenever the whole-record one is not better by the threshold located wrong onsets as often as
right ones.)

What the answer says (:func:`acting_part`): the onset, and the fits (%) of the model without the finding and of
the final model on the samples from the onset on, so that the finding is judged where it acts and is not
credited with the healthy part.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainCandidate, ChainContext
from valve_emulator.diagnosis.fit.data import Problem, fit_percent
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.records import Model, Option

__all__ = ["ONSETS", "EARLY_SHARE", "MIN_BAND", "LateOnset", "Onset", "onset_option", "acting_part", "onset_of"]

#: Onsets of the coarse stage, as fractions of the fit part: the physics acts on a quarter of it at least, so
#: that a short stretch near the end (a few cycles of a load the linear part misses) is not fitted as a valve
#: that began to stick there.
ONSETS = tuple(np.round(np.linspace(0.1, 0.75, 14), 3))
#: The onset is searched only when the whole-record option's improvement of the residual lies less than this
#: share in the first half of the fit part (:func:`_early_share`; uniform physics puts about half there).
EARLY_SHARE = 0.4
#: Least band (first OP-sized parameter) of a late fit, as a fraction of the OP span (see :func:`_material`).
MIN_BAND = 0.05


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
            rows = np.flatnonzero(starts == k0)
            xs = x if x.ndim == 1 else x[:, rows]
            out[:, rows] = xs[:, None] if x.ndim == 1 else xs
            if T - k0 >= 2:  # the inner candidate acts from the onset sample on, started there
                out[k0:, rows] = self.inner.apply(xs[k0:], params[rows, :-1], ctx)
        return out

    def parameters(self, p: np.ndarray) -> dict:
        return {**self.inner.parameters(p[:-1]), "onset_s": round(float(p[-1]), 1)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %") -> str:
        return f"{self.inner.describe(p[:-1], nominal, units)}, from t ≈ {p[-1]:.4g} s on"


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

    def to_json(self) -> dict:
        return {"onset_s": round(self.onset_s, 1), "fit_before": round(self.fit_before, 2),
                "fit_after": round(self.fit_after, 2)}


def _coarse_rows(fitter: Fitter, cand: ChainCandidate, ctx) -> np.ndarray:
    """The candidate's coarse grid at every onset of :data:`ONSETS` within the fit part."""
    w0, w1 = fitter.p.train
    onsets = (w0 + np.asarray(ONSETS) * (w1 - w0)) * fitter.p.dt
    inner = cand.grid(ctx)
    return np.vstack([LateOnset.with_onset(inner, t0) for t0 in onsets])


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


def onset_option(fitter: Fitter, model: Model, cand: Candidate, plain: Option) -> Option | None:
    """``cand`` added to ``model`` acting from a fitted onset on (see the module docstring); None without a
    nominal model, for a candidate that cannot start late or an option that frees the dead time with it."""
    if not (fitter.nominal.given and getattr(cand, "may_start_late", False)) or plain.added != (cand.name,):
        return None
    if _early_share(fitter.p, model, plain.model) >= EARLY_SHARE:
        return None
    late = LateOnset(cand)
    scorer = fitter.scorer
    ctx, aim = scorer.ctx(model), scorer.aim(model)
    active = model.by_slot()
    rows = _coarse_rows(fitter, cand, ctx)
    best = None
    for st in {id(s): s for s in (model.fit.structure, plain.model.fit.structure)}.values():
        sse, _ = scorer.sse_grid(active, ctx, late, rows, st, None, aim)
        i = int(np.argmin(sse[:, 0]))
        if best is None or sse[i, 0] < best[0]:
            best = (float(sse[i, 0]), rows[i], st)
    _, row, st = best
    scan_surface = None
    scan = cand.scan(ctx)
    if scan is not None:
        scan = LateOnset.with_onset(scan, row[-1])
        sse, _ = scorer.sse_grid(active, ctx, late, scan, st, None, aim)
        row = scan[int(np.argmin(sse[:, 0]))]
        scan_surface = fitter.surface(cand.name, scan, sse[:, 0])
    r = fitter.refine(model, late, row, st, model.delay_free, joint=False)
    if not _material(cand, r.active[cand.slot].params, ctx.op_span):
        return None
    m = scorer.model(r.active, r.fit, model.delay_free, r.flow, target=aim.y)
    return Option(added=(cand.name,), model=m, coarse=None, scan=scan_surface, fine=r.fine)


def onset_of(model: Model, name: str) -> float | None:
    """The onset (s) of finding ``name`` in ``model``, None when it acts from the start."""
    act = next((a for a in model.active if a.name == name), None)
    if act is None or not isinstance(act.candidate, LateOnset):
        return None
    return float(act.params[-1])


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
