r"""Which samples the coarse stages of a candidate search score: the whole fit part, or windows over it.

The first two stages of every candidate search (:mod:`~valve_emulator.diagnosis.fit.fitter`: the coarse grid
× pole hypotheses, the stiction scan) only choose where the refinement starts; the refinement, the polishes,
BIC, the intervals and everything the answer reports are computed on the whole fit part. On a long record the
two stages are most of the time (at 100,000 samples 2.5 + 7.3 s of 21.6), and they grow with the record while
what they decide does not. So on a fit part of at least :data:`LONG` samples they score :data:`COUNT` windows
of :data:`LENGTH` samples instead, spread evenly from the fit part's first sample to its last (the first window
starts where the fit part starts, the last ends where it ends), each SSE summed over the windows. Each window
is its own sub-record: the chain and the linear filters start afresh :data:`LEAD_IN` samples before its scored
samples (a valve's unknown initial state and the filter's transient are forgotten there, as in the record's own
burn-in), with the same scaling, dead-time grid and OP span as the record, so every window sees the same grid
rows. Shorter fit parts are scored whole, as before.

Why windows and not the record decimated (every k-th sample): measured on the proof cases (2026-11-26), a
decimated record changed the answer at every k tried (k = 2, 4, 8: a deadband, or J 0.13 for J = 2; k = 3:
J 1.82) — a stick-slip valve moves at single samples, and a coarser step shifts its slips and the dead-time
grid. Windows of 500 samples (300 of lead-in) left all 28 documents of ``bench/diagnosis_identity.py --draws 1``
identical; windows of 250 (150 of lead-in) changed six (a deadband for a valve without offset, a dead time two
samples off). Windows of 1,500 samples (500 of lead-in) gave the proof case's answer, S, J and intervals at
30,000 and 100,000 samples, but on a sticky level loop of 40,000 samples (independent simulator, nominal model
given) J 1.38 instead of 1.59 and one finding fewer; windows of 3,000 (1,000 of lead-in), the ones here, gave that
loop's document as the whole record does.

Why evenly spread windows and not the record's first part: physics that starts late in a long record (a valve
that begins to stick halfway) must reach the windows; the last window ends where the fit part ends. A stretch
between two windows can be missed by these two stages, which then give the refinement a worse start; it is not
lost, since every candidate is still refined and judged on the whole record. But where the loop's behaviour is
located to change part-way before the search (:func:`~valve_emulator.diagnosis.explain.onset.suspect_onset`),
windows weigh the part after the change by how many of them fall there, not by its length: at 100,000 samples
with a valve sticking from t = 70,000 s the first finding became a deadband instead of stiction from 68,125 s.
Such a record's coarse stages score all of it (:class:`~valve_emulator.diagnosis.fit.fitter.Fitter`'s
``windowed``), and so do those of a record without a nominal model: there the coarse stage also chooses the
linear part among pole hypotheses with time constants up to a tenth of the record, longer than a window, and a
sticky flow loop of 40,000 samples as plant data got S 4.59 on windows of 1,500 and 4.81 on windows of 3,000
instead of 5.08 (its interval 4.83–5.27) on the whole record.

The refinement stays on the whole record: its two passes on windows moved J from 2.01 to 1.41 with 500-sample
lead-ins (1.84 with 5,000); its first pass alone on these windows gave the same answer on the proof case at
100,000 samples but moved a sticky flow loop's S from 5.08 to 5.03 and J from 2.58 to 2.46 at 40,000 samples
(independent simulator). The intervals' profile on windows widened J's interval from 1.92–2.09 to 1.25–2.01.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext
from valve_emulator.diagnosis.fit.data import Problem
from valve_emulator.diagnosis.fit.linear import highpass
from valve_emulator.diagnosis.fit.records import Model
from valve_emulator.diagnosis.fit.scorer import Aim, Scorer
from valve_emulator.physics._arrays import kernel_array

__all__ = ["COUNT", "LEAD_IN", "LENGTH", "LONG", "Part", "Window", "coarse_parts", "coarse_windows",
           "window_scorer"]

#: Windows a long fit part is scored on by the coarse stages.
COUNT = 4
#: Scored samples of one window.
LENGTH = 3000
#: Samples before a window's scored ones over which its chain and filters start afresh (never scored).
LEAD_IN = 1000
#: Fit parts of at least this many samples are scored on windows: twice what the windows score, so that they
#: never score more than half of it.
LONG = 2 * COUNT * LENGTH


@dataclass(frozen=True)
class Window:
    """One window of the record: its sub-record starts at ``lead``, its scored samples are ``[start, stop)``
    (record samples); ``[lead, start)`` is its lead-in."""

    lead: int
    start: int
    stop: int

    @property
    def scored(self) -> int:
        return self.stop - self.start


@dataclass(frozen=True, eq=False)
class Part:
    """One stretch of the record a coarse stage scores: the scorer of its (sub-)record, the chain context and
    the aim of the model being extended on it."""

    scorer: Scorer
    ctx: ChainContext
    aim: Aim

    @property
    def n_fit(self) -> int:
        return self.scorer.p.n_fit


def coarse_windows(train: tuple[int, int]) -> tuple[Window, ...]:
    """The windows the coarse stages score on fit part ``train`` = ``(w0, w1)``; none (the whole fit part is
    scored) when it is shorter than :data:`LONG`. Window ``i`` starts at ``w0 + i·(w1 − w0 − L)/(COUNT − 1)``;
    its lead-in is :data:`LEAD_IN` samples, or as many as lie before it."""
    w0, w1 = train
    if w1 - w0 < LONG:
        return ()
    out = []
    for i in range(COUNT):
        start = w0 + int(round(i * (w1 - w0 - LENGTH) / (COUNT - 1)))
        out.append(Window(lead=max(0, start - LEAD_IN), start=start, stop=start + LENGTH))
    return tuple(out)


def window_problem(problem: Problem, w: Window) -> Problem:
    """``problem``'s sub-record of window ``w``, its fit part the window's scored samples (same scaling,
    dead-time grid and OP span)."""
    sl = slice(w.lead, w.stop)
    return replace(problem, t=problem.t[sl], op=problem.op[sl], pv=problem.pv[sl], y=problem.y[sl],
                   train=(w.start - w.lead, w.stop - w.lead))


def window_scorer(scorer: Scorer, w: Window) -> Scorer:
    """A scorer of window ``w`` of ``scorer``'s record (same nominal model and library)."""
    return Scorer(window_problem(scorer.p, w), scorer.nominal, scorer.library)


def _window_aim(scorer: Scorer, w: Window, model: Model) -> Aim:
    """The model's aim on a window: the window's scaled PV, or the model's target sliced (filtered afresh)."""
    if model.target is None:
        return scorer.aim(None)
    y = model.target[w.lead:w.stop]
    return Aim(y, kernel_array(y if scorer.lam is None else highpass(y, scorer.lam)))


def coarse_parts(full: Scorer, windows: tuple[Window, ...], scorers: tuple[Scorer, ...], model: Model,
                 cand: Candidate) -> tuple[Part, ...]:
    """What the coarse stages of ``cand`` added to ``model`` score: one part per window (``scorers`` the
    windows' own), or the whole record when there are no windows or when ``cand``'s coarse grid or scan read on
    a window differs from the record's (a grid taken from the data, e.g. a saturation's OP percentiles: the
    windows' SSEs would not be of the same rows)."""
    ctx = full.ctx(model)
    whole = (Part(full, ctx, full.aim(model)),)
    if not windows:
        return whole
    grid, scan = cand.grid(ctx), cand.scan(ctx)
    parts = []
    for w, s in zip(windows, scorers):
        c = s.ctx(model)
        if not (_same(cand.grid(c), grid) and _same(cand.scan(c), scan)):
            return whole
        parts.append(Part(s, c, _window_aim(s, w, model)))
    return tuple(parts)


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(a, b)
