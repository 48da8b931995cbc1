r"""Physics that starts part-way through a record: when it starts, and its fit on the part where it acts.

A valve can start to stick in the middle of a long record. Fitted over the whole record, a stiction valve
must also explain the healthy part, where the valve followed OP: the fit settles on a smaller band, and what
it leaves over is taken up by physics that is not there (a dead-time error, a characteristic). So for every
candidate that :attr:`~valve_emulator.diagnosis.candidates.base.ChainCandidate.may_start_late`, the search
also fits it as :class:`~valve_emulator.diagnosis.candidates.base.LateOnset`: the slot passes its signal
through before an onset time ``t0`` and the candidate acts from ``t0`` on, its state started there.

Fitting the onset (:func:`onset_option`)
---------------------------------------
1. **coarse**: the candidate's coarse grid at each onset of :data:`ONSETS` fractions of the fit part, scored
   at the poles of the model being extended and of the candidate's own whole-record option (the onset and
   the band trade off: a coarse grid over both, not a line search from the whole-record fit);
2. **scan**: the candidate's global scan (fine in S for stiction) at the best onset;
3. **refine**: the fitter's refinement of the candidate's parameters, its fine grid also moving the onset
   by :attr:`~valve_emulator.diagnosis.candidates.base.LateOnset.onset_step` of the record (twice), the
   threshold parameters centred.

The search (:mod:`~valve_emulator.diagnosis.explain.search`) offers the late option in place of the
whole-record one when it lowers BIC by the search's own threshold: the onset is one more parameter. (Measured on
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

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainCandidate, LateOnset
from valve_emulator.diagnosis.fit.data import Problem, fit_percent
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.records import Model, Option

__all__ = ["ONSETS", "Onset", "onset_option", "acting_part", "onset_of"]

#: Onsets of the coarse stage, as fractions of the fit part (the physics acts on a tenth of it at least).
ONSETS = tuple(np.round(np.linspace(0.1, 0.9, 17), 3))


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


def onset_option(fitter: Fitter, model: Model, cand: Candidate, plain: Option) -> Option | None:
    """``cand`` added to ``model`` acting from a fitted onset on (see the module docstring); None for a
    candidate that cannot start late or an option that frees the dead time with it."""
    if not getattr(cand, "may_start_late", False) or plain.added != (cand.name,):
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
