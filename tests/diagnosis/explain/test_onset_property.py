"""A valve that starts to stick part-way, on loops the search did not make.

The loops are the independent simulator's ``late_onset`` family (:mod:`valve_emulator.benchmark.independent`):
a level or a self-regulating plant, a PI one sample late, a wandering load, and a valve that is healthy until an
onset drawn in the middle 60 % of the record and sticks from then on (data-driven or Karnopp friction, S 2–6 %,
with or without an actuator lag). Each loop is diagnosed with its nominal model (the linear part and the tuning,
an ideal valve) and as plant data (no model, OP declared as % travel).

The property asked for: the onset within 10 % of the record, S and J within 25 % and no finding besides the
valve's own (its friction, and an actuator lag where the loop has one) in at least 9 draws of 10. J is judged
against the J of the 2005 valve that best reproduces the drawn valve's own stem travel (:func:`valve_2005`):
the drawn valve's J is not that J in 8 draws of 20. It is not met: measured 5/20 with a model and 7/20 without
(strict xfails below). What holds is checked at the rates measured (seed 32), one draw of slack each: the change
point locates the onset before any fit in 17 draws of 20; the answer is stiction in 19/20 both ways; an onset it
reports is within a tenth of the record in 16 of 18 both ways; stiction from an onset within a tenth, with S
within 25 %, in 15/20 with a model and 12/20 without. What stands in the way, measured (a draw may miss for
several reasons): J off by more than 25 % (11 draws with a model, 8 without; 7 with a model miss on J alone:
Karnopp stems whose slip the 2005 valve does not reproduce, J traded against the linear part's gain); extra
dead-time, saturation, disturbance and characteristic findings that hold after the onset under both noise models
(5 with a model, 4 without); a deadband (J = 0) chosen over stiction (2 with a model, 5 without); S off by more
than 25 % (3 and 5); the change point a fifth of the record early (one loop that starts to cycle long after its
valve starts to stick, both ways, and one more each way); no onset reported (2 each way).

Time: about 4 minutes for the 20 draws, both ways (about 3 s a diagnosis on an idle core; 15–30 s on a machine
shared by six processes).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pytest
from unseen_loops import LATE_ONSET, Draw, diagnosed, diagnosed_all, loop

from valve_emulator.diagnosis.explain.onset import suspect_onset
from valve_emulator.physics.actuator import actuator_response
from valve_emulator.physics.stiction import simulate_many

DRAWS = 20
SEED = 32
#: The tolerances of the property: the onset within this fraction of the record, S and J within this fraction.
ONSET_TOL, SIZE_TOL = 0.10, 0.25


def _loop(i: int) -> tuple:
    return loop("late_onset", (SEED, i))


def _stem_rms(op: np.ndarray, mv: np.ndarray, S: np.ndarray, J: np.ndarray) -> np.ndarray:
    """RMS (% travel) of each 2005 valve's (S, J) travel on ``op`` against the stem travel ``mv``, at its best
    initial direction and with the operating point free (a constant offset)."""
    out = []
    for direction in (1, -1):
        r = mv[:, None] - simulate_many(op, S, J, direction=direction)
        out.append(np.sqrt(np.mean((r - r.mean(axis=0)) ** 2, axis=0)))
    return np.minimum(*out)


@functools.cache
def valve_2005(i: int) -> tuple[float, float]:
    """The (S, J) of the 2005 valve (:mod:`valve_emulator.physics.stiction`, the model the diagnosis reports)
    that best reproduces draw ``i``'s own stem travel from its OP after the onset: no plant, no noise, the
    actuator lag applied to OP where it acts before the friction, OP taken as it is or one sample earlier.

    Why: the drawn valve is a Karnopp stem or a data-driven valve written from its definition, whose S and J
    are defined as the 2005 model's, but whose cycles differ in detail (a Karnopp stem re-sticks during slow
    motion, the data-driven one rests after 1.5 samples of a held input). Fitted to the valve's own OP→MV,
    the 2005 model reproduces S but not J: its J misses the drawn J by more than 25 % in 8 draws of 20
    (:func:`test_the_2005_valve_fitted_to_the_drawn_valve_alone_reproduces_its_S_but_not_always_its_J`),
    so the drawn J cannot be the measure of a diagnosis' J; this one can."""
    rec, truth, _ = _loop(i)
    valve = truth["valve"]
    k0 = int(np.ceil(truth["onset"] / rec.dt)) + 1
    op = np.clip(np.asarray(rec.op, dtype=float), 0.0, 100.0)
    if valve["actuator_lag"] > 0 and valve["order"] == "lag_first":
        op = actuator_response(op, valve["actuator_lag"], rec.dt)
    mv = np.asarray(truth["mv"], dtype=float)[k0:]
    S, J = (a.ravel() for a in np.meshgrid(truth["S"] * np.linspace(0.3, 2.0, 69),
                                           truth["S"] * np.linspace(0.0, 1.6, 41)))
    best = min((float(e[j]), float(S[j]), float(J[j]))
               for e in (_stem_rms(op[k0 - shift:op.size - shift], mv, S, J) for shift in (0, 1))
               for j in [int(np.argmin(e))])
    return best[1], best[2]


def j_error(J: float, i: int) -> float:
    """Error of a diagnosed J against the J a 2005 valve has for draw ``i`` (:func:`valve_2005`), relative to
    the larger of that J and the drawn one (a drawn valve whose 2005 J is 0 is judged on the drawn J's scale)."""
    J_2005, J_drawn = valve_2005(i)[1], _loop(i)[1]["J"]
    return abs(J - J_2005) / max(J_2005, J_drawn)


@dataclass(frozen=True)
class Outcome:
    """One diagnosis against the loop's truth."""

    answer: str
    onset_err: float | None   # |reported − true onset| / record length; None when no onset is reported
    S_err: float | None       # relative error of the friction's S in % travel; None without friction
    J_err: float | None       # error of its J against the 2005 valve's (:func:`j_error`)
    extra: tuple[str, ...]    # findings that are not the valve's own

    @property
    def holds(self) -> bool:
        """The property of one draw: stiction, its onset and its size within tolerance, nothing else found."""
        return (self.answer == "stiction" and self.onset_err is not None and self.onset_err <= ONSET_TOL
                and self.S_err is not None and self.S_err <= SIZE_TOL and self.J_err <= SIZE_TOL and not self.extra)


@functools.cache
def _outcome(i: int, mode: str) -> Outcome:
    d = diagnosed(Draw("late_onset", (SEED, i), mode))
    rec, truth, doc = d.recording, d.truth, d.doc
    findings = doc.get("findings") or []
    own = {"stiction", "deadband"} | ({"actuator_lag"} if truth["valve"]["actuator_lag"] > 0 else set())
    onsets = [f["onset"]["onset_s"] for f in findings if f.get("onset")]
    length = float(rec.t[-1] - rec.t[0])
    travel = (doc["friction"] or {}).get("travel")
    S_err = J_err = None
    if travel is not None:
        S_err = abs(travel["S"]["value"] - truth["S"]) / truth["S"]
        J_err = j_error(travel["J"]["value"], i)
    return Outcome(answer=doc["answer"], onset_err=abs(onsets[0] - truth["onset"]) / length if onsets else None,
                   S_err=S_err, J_err=J_err, extra=tuple(f["physics"] for f in findings if f["physics"] not in own))


def _outcomes(mode: str) -> list[Outcome]:
    """Every draw's outcome in ``mode``; the diagnoses shared with the other property tests (and workers)."""
    diagnosed_all(key for key in LATE_ONSET if key.mode == mode)
    return [_outcome(i, mode) for i in range(DRAWS)]


def _count(mode: str, test) -> int:
    return sum(bool(test(o)) for o in _outcomes(mode))


@pytest.mark.slow
def test_the_2005_valve_fitted_to_the_drawn_valve_alone_reproduces_its_S_but_not_always_its_J():
    """The measure of J (:func:`valve_2005`): fitted to the valve's own OP→MV, S within 25 % of the drawn S in
    19 draws of 20, J within 25 % of the drawn J in 12 of 20 only (Karnopp stems 4 of 9)."""
    S_ok = J_ok = 0
    for i in range(DRAWS):
        truth = _loop(i)[1]
        S, J = valve_2005(i)
        S_ok += abs(S - truth["S"]) <= SIZE_TOL * truth["S"]
        J_ok += abs(J - truth["J"]) <= SIZE_TOL * truth["J"]
    assert S_ok >= 0.9 * DRAWS
    assert J_ok <= 0.75 * DRAWS


@pytest.mark.slow
def test_the_onset_is_located_before_any_fit_within_a_tenth_of_the_record():
    """The change point in the control error's energy alone (no model, no search): measured 17/20."""
    hits = 0
    for i in range(DRAWS):
        rec, truth, _ = _loop(i)
        found = suspect_onset(rec.pv, rec.sp)
        hits += found is not None and abs(rec.t[found.sample] - truth["onset"]) <= ONSET_TOL * (rec.t[-1] - rec.t[0])
    assert hits >= 0.85 * DRAWS


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least", "wrong"), [("model", 15, 3), ("plant", 15, 3)])
def test_an_onset_the_answer_reports_is_within_a_tenth_of_the_record(mode, least, wrong):
    """Measured: 16 of 18 reported onsets both ways. The misses: the change point's (1080 s for 1679 s, both
    ways; with a model also 1733 s for 2385 s, without 2310 s for 2009 s, just over a tenth)."""
    reported = [o.onset_err for o in _outcomes(mode) if o.onset_err is not None]
    assert sum(e <= ONSET_TOL for e in reported) >= least
    assert sum(e > ONSET_TOL for e in reported) <= wrong


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 18), ("plant", 18)])
def test_a_valve_that_starts_to_stick_part_way_is_answered_stiction(mode, least):
    """Measured 19/20 both ways: a valve that starts late counts where the free run alone would not let it
    (under the drifting-load noise model, :meth:`~valve_emulator.diagnosis.explain.search.Search.late_counts`)."""
    assert _count(mode, lambda o: o.answer == "stiction") >= least


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 14), ("plant", 11)])
def test_stiction_is_found_from_its_onset_with_its_band_at_the_rate_reached(mode, least):
    """The part of the property the search reaches: the answer is stiction, from an onset within a tenth of the
    record, with S within 25 % (J and the other findings are left to the strict xfail below). Measured 15/20 with
    a model, 12/20 without."""
    reached = _count(mode, lambda o: o.answer == "stiction" and o.onset_err is not None and o.onset_err <= ONSET_TOL
                     and o.S_err is not None and o.S_err <= SIZE_TOL)
    assert reached >= least


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured 5/20 with a model and 7/20 without (see the module docstring)")
@pytest.mark.parametrize("mode", ["model", "plant"])
def test_onset_and_size_within_tolerance_and_nothing_else_in_nine_draws_of_ten(mode):
    assert _count(mode, lambda o: o.holds) >= 0.9 * DRAWS
