r"""A recording made ready for identification: scaled PV, scoring windows and the held-out part.

The record of ``T`` samples is split as

====================  ======================================================================
``[0, w0)``           burn-in: room for the longest dead time tried, the plant's initial transient and
                      the valve's unknown initial state (never scored; :func:`prepare` sets it from the
                      record and the nominal model, :func:`with_burn_in` lengthens it for the candidates)
``[w0, w1)``          fit part: every parameter is fitted here and BIC is computed here
``[w1, T)``           held-out part, the last :data:`HELD_OUT` of the record: the free-run fit reported
                      as ``fit_before``/``fit_after`` is measured here only
====================  ======================================================================

That is ``validation="split"``, used with a nominal model. Without one (real data, ``"twofold"``) the fit
part runs to the end of the record and the held-out fit is cross-validated on two blocks instead
(:func:`folds`, :mod:`~valve_emulator.diagnosis.fit.crossval`): on plant data the evidence — a valve that
slips twice in two hours — can all lie in the last 30 %, which a single split would never fit.

PV is centred and scaled by the fit part's mean and standard deviation before fitting (conditioning only:
the offset regressor absorbs any constant, and BIC differences do not depend on the scale).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from valve_emulator.diagnosis.fit.linear import highpass
from valve_emulator.recordings.recording import Recording, RecordingError

__all__ = ["Problem", "prepare", "prefilter_for", "folds", "fold_windows", "held_out_start", "HELD_OUT", "MIN_SAMPLES",
           "VALIDATIONS", "fit_percent", "UninformativeData", "with_burn_in", "BURN_CAP", "WIDEN", "delay_at_end",
           "widens"]

#: Fraction of the record, at its end, held out from fitting.
HELD_OUT = 0.3
#: Fewest samples the diagnosis accepts whatever the model (burn-in, fit part and held-out part).
MIN_SAMPLES = 200
#: How the held-out fit is measured: one split (the last :data:`HELD_OUT` held out) or two blocked folds.
VALIDATIONS = ("split", "twofold")
#: Burn-in bounds, as fractions of the record.
_BURN_MIN, _BURN_MAX = 0.05, 0.25
#: Longest burn-in (fraction of the record) that candidates' initial states may claim (:func:`with_burn_in`).
BURN_CAP = 0.35
#: Without a model, how many times farther the dead-time grid reaches when a search on the usual grid (0..100
#: samples, at most T/20) ends with its dead time on the grid's last point: an edge is not a value (widen the range,
#: or report a bound). The grid is widened only where its end was the 100-sample cap (records of 2000 samples or
#: more), twice as far as the record allows; where it was T/20, a dead time on it is reported as a bound: widened
#: there too, three of the 80 shared plant windows (751 samples, or halves of 375) changed answer, two for the worse.
WIDEN = 2


class UninformativeData(RecordingError):
    """A recording that is valid but cannot inform a diagnosis: too few rows, or a constant OP or PV.

    Unlike a broken file, this is an answer about the data ("cannot tell"), so callers can tell it apart by
    type. The message is ``"<source>: <reason>"``.

    Attributes
    ----------
    source : the recording's name.
    reason : what is missing, without the source (names the line or the column).
    line : the file line the reason points at (None when it names a column).
    column : the constant column (None when the record is too short).
    """

    def __init__(self, source: str, reason: str, *, line: int | None = None, column: str | None = None) -> None:
        super().__init__(f"{source}: {reason}")
        self.source, self.reason, self.line, self.column = source, reason, line, column


def held_out_start(T: int) -> int:
    """First sample of the held-out part, the last :data:`HELD_OUT` of a record of ``T`` samples."""
    return int(round((1.0 - HELD_OUT) * T))


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Free-run fit in percent, ``100·(1 − ‖y − ŷ‖ / ‖y − ȳ‖)`` (can be negative)."""
    dev = np.linalg.norm(y - np.mean(y))
    if dev == 0.0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - y_hat) / dev))


@dataclass(frozen=True, eq=False, kw_only=True)
class Problem:
    """The data of one diagnosis (arrays read-only).

    Attributes
    ----------
    t, op, pv : the recording's time (s), controller output (% travel) and PV (engineering units).
    y : PV centred and scaled, ``(pv − y_mean) / y_scale``.
    dt : sample step (s).
    train : ``(w0, w1)``, the fit part; ``test`` is ``(w1, T)``.
    delays : integer dead times (samples) that every fit searches.
    op_span : robust OP range, 99.5th − 0.5th percentile of the fit part (% travel).
    prefilter : λ of the high-pass prefilter for integrating plants (see
        :func:`~valve_emulator.diagnosis.fit.linear.highpass`), None to fit PV itself; the held-out fit is
        measured through it too (:meth:`Problem.validated`).
    source : the recording's name, for messages.
    validation : one of :data:`VALIDATIONS`; with ``"twofold"`` the fit part runs to the end.
    stops : where OP is at 0 and 100 % travel in ``op``'s frame (see
        :attr:`~valve_emulator.diagnosis.fit.frame.Frame.stops`).
    """

    t: np.ndarray
    op: np.ndarray
    pv: np.ndarray
    y: np.ndarray
    y_mean: float
    y_scale: float
    dt: float
    train: tuple[int, int]
    delays: np.ndarray
    op_span: float
    prefilter: float | None = None
    source: str = ""
    validation: str = "split"
    stops: tuple[float, float] = (0.0, 100.0)

    @property
    def T(self) -> int:
        return int(self.t.shape[0])

    @property
    def test(self) -> tuple[int, int]:
        return self.train[1], self.T

    @property
    def n_fit(self) -> int:
        return self.train[1] - self.train[0]

    def to_pv(self, y_scaled: np.ndarray) -> np.ndarray:
        return y_scaled * self.y_scale + self.y_mean

    def heldout_fit(self, y_scaled_hat: np.ndarray) -> float:
        """Free-run fit (%) of a prediction on the held-out part, in the validation domain (:meth:`validated`):
        what the search's rule compares."""
        a, b = self.test
        return fit_percent(self.validated(self.y)[a:b], self.validated(y_scaled_hat)[a:b])

    def pv_heldout_fit(self, y_scaled_hat: np.ndarray) -> float:
        """Free-run fit (%) of a prediction on the held-out part, on PV itself: what is reported."""
        a, b = self.test
        return fit_percent(self.y[a:b], y_scaled_hat[a:b])

    def validated(self, y_scaled: np.ndarray) -> np.ndarray:
        """What a held-out fit compares: PV itself, or for an integrating plant (a ``prefilter``) PV through the
        high-pass prefilter (:func:`~valve_emulator.diagnosis.fit.linear.highpass`), started at the record's
        first sample.

        Why: an integrating plant turns any slow load it is not told about into a ramp, so a free run over the
        held-out part drifts away by an amount no valve model changes (fits of −2000 % for the nominal model of
        a level loop with a wandering load), and a rule that asks a finding to raise that fit by half a point
        rejects the right valve as readily as a wrong one. Through the prefilter the drift is forgotten within
        :math:`T_c` samples while every slip still counts. The fits reported (``fit_before``, ``fit_after``)
        stay on PV itself (:meth:`pv_heldout_fit`)."""
        if self.prefilter is None:
            return y_scaled
        return highpass(y_scaled, float(self.prefilter))


def prefilter_for(response_time: float, dt: float) -> float:
    """λ of the high-pass prefilter for an integrating plant: ``1 − 1/T_c``, ``T_c`` in samples.

    ``T_c`` is three response times (dead time + time constants), kept within [20, 200] samples: long enough
    that the prefiltered PV keeps the shape of a cycle, short enough that a slip-timing error is forgiven.
    """
    tc = float(np.clip(3.0 * response_time / dt, 20.0, 200.0))
    return 1.0 - 1.0 / tc


def folds(problem: Problem) -> tuple[tuple[tuple[int, int], tuple[int, int]], ...]:
    """The two blocked folds ``((fit, held out), ...)`` of a ``"twofold"`` problem.

    Fold A fits ``[w0, a)`` and holds out the last :data:`HELD_OUT` ``[a, T)``; fold B fits ``[b, T)`` and
    holds out ``[w0, b)``, the first :data:`HELD_OUT` after the burn-in. Free-run (output-error)
    predictions depend on the recorded OP only, never on past PV, so a held-out block may precede the
    samples fitted without leaking them.
    """
    return fold_windows(problem.T, problem.train[0])


def fold_windows(T: int, w0: int) -> tuple[tuple[tuple[int, int], tuple[int, int]], ...]:
    """:func:`folds` of a record of ``T`` samples whose burn-in ends at ``w0``."""
    a = held_out_start(T)
    b = max(w0 + 1, int(round(HELD_OUT * T)))
    return ((w0, a), (a, T)), ((b, T), (w0, b))


def _delay_grid(dt: float, T: int, nominal_delay: float | None, reach: int = 1) -> np.ndarray:
    """Dead times tried: around the nominal one (±max(4, nominal) samples), or without a model 0..min(100, T/20)
    samples; widened (``reach`` = :data:`WIDEN`), 0..100·reach samples, never so far that the record is shorter
    than ten times the longest dead time (:func:`prepare`'s need)."""
    if nominal_delay is None:
        last = min(100, T // 20) if reach == 1 else min(100 * reach, T // 10 - 1)
        return np.arange(0, int(last) + 1)
    d = int(round(nominal_delay / dt))
    r = int(min(50, max(4, d)))
    return np.arange(max(0, d - r), d + r + 1)


def delay_at_end(problem: Problem, delay: float) -> bool:
    """Whether a dead time (s) sits on the end of the problem's dead-time grid, within one sample of its last
    point (the grid's step: the polish of a dead time between grid points stops at the last one, and one that
    converged a fraction of a sample inside it was still held by it): the edge of the range searched, which
    says the dead time is at least that, not what it is."""
    return delay >= (float(problem.delays.max()) - 1.0) * problem.dt


def widens(problem: Problem) -> bool:
    """Whether a problem without a model may have its dead-time grid widened (:data:`WIDEN`): it has not been
    yet, its grid ends at the 100-sample cap, not at T/20 (:data:`WIDEN`), and the record allows a longer one."""
    T = problem.T
    return int(problem.delays.max()) == 100 <= T // 20 and int(_delay_grid(problem.dt, T, None, WIDEN).max()) > 100


def prepare(rec: Recording, *, nominal_delay: float | None = None, settle_time: float = 0.0,
            prefilter: float | None = None, validation: str = "split",
            stops: tuple[float, float] = (0.0, 100.0), reach: int = 1) -> Problem:
    """Check a recording and split it (see the module docstring).

    Parameters
    ----------
    rec : the recording (``t``, ``op``, ``pv`` used; ``sp``/``mv`` may be absent).
    nominal_delay : the nominal model's dead time (s), which centres the dead-time grid; None = no model.
    settle_time : the nominal plant's settling time (s), a lower bound for the burn-in.
    prefilter, stops : see :class:`Problem`.
    reach : without a model, how many times the usual dead-time grid is searched (1, or :data:`WIDEN` when a fit
        on the usual grid put its dead time on the grid's end).
    validation : ``"split"`` (hold out the last :data:`HELD_OUT`) or ``"twofold"`` (fit on all, cross-validate).

    Raises
    ------
    RecordingError
        Fewer samples than the diagnosis needs (naming the last line of the file), a non-finite value, a
        constant OP or PV, or a non-uniform time axis (lines counted as in the CSV: the header is line 1).
    """
    if validation not in VALIDATIONS:
        raise ValueError(f"validation must be one of {', '.join(VALIDATIONS)}, got {validation!r}")
    T = len(rec)
    src = rec.source or "recording"
    dt = rec.dt if T >= 2 else 1.0
    delays = _delay_grid(dt, T, nominal_delay, reach)
    need = max(MIN_SAMPLES, 10 * (int(delays.max()) + 1))
    if need > T:
        raise UninformativeData(src, f"line {T + 1}: {T} data row(s), the diagnosis needs at least {need} "
                                     f"(burn-in for a dead time of up to {int(delays.max())} samples, a fit part "
                                     "and a held-out part)", line=T + 1)
    for name, col in (("t", rec.t), ("op", rec.op), ("pv", rec.pv)):
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise RecordingError(f"{src}: line {int(bad[0]) + 2}, column {name!r}: {float(col[bad[0]])!r} is not a "
                                 "finite number")
    steps = np.diff(rec.t)
    if np.any(np.abs(steps - dt) > 0.01 * dt):
        i = int(np.flatnonzero(np.abs(steps - dt) > 0.01 * dt)[0]) + 1
        raise RecordingError(f"{src}: line {i + 2}: sample step {steps[i - 1]!r} s differs from the median "
                             f"{dt!r} s by more than 1 %; the diagnosis needs uniform sampling")
    w1 = held_out_start(T) if validation == "split" else T
    burn = max(int(delays.max()) + 4, int(np.ceil(settle_time / dt)), int(_BURN_MIN * T))
    w0 = min(burn, int(_BURN_MAX * T))
    for name, col in (("op", rec.op), ("pv", rec.pv)):
        if np.ptp(col[w0:w1]) == 0.0:
            raise UninformativeData(src, f"column {name!r} is constant over lines {w0 + 2}-{w1 + 1}; nothing "
                                         "to identify", column=name)
    y_mean = float(np.mean(rec.pv[w0:w1]))
    y_scale = float(np.std(rec.pv[w0:w1]))
    y = (np.asarray(rec.pv) - y_mean) / y_scale
    lo, hi = np.percentile(rec.op[w0:w1], [0.5, 99.5])
    arrays = [np.array(a, dtype=float) for a in (rec.t, rec.op, rec.pv, y)]
    for a in arrays:
        a.setflags(write=False)
    t, op, pv, y = arrays
    return Problem(t=t, op=op, pv=pv, y=y, y_mean=y_mean, y_scale=y_scale, dt=float(dt), train=(w0, w1),
                   delays=delays, op_span=float(max(hi - lo, 1e-6)), prefilter=prefilter, source=src,
                   validation=validation, stops=stops)


def with_burn_in(problem: Problem, burn: int) -> Problem:
    """``problem`` with its fit part starting after ``burn`` samples (at most :data:`BURN_CAP` of the record),
    when that is later than it starts: every candidate's unknown initial state is forgotten before a model is
    scored (``burn`` from :func:`~valve_emulator.diagnosis.fit.scorer.library_burn_in`)."""
    w0, w1 = problem.train
    if burn <= w0:
        return problem
    return replace(problem, train=(min(burn, int(BURN_CAP * problem.T)), w1))
