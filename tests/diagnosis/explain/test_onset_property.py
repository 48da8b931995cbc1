"""A valve that starts to stick part-way, on loops the search did not make.

The loops are the independent simulator's ``late_onset`` family (:mod:`valve_emulator.benchmark.independent`):
a level or a self-regulating plant, a PI one sample late, a wandering load, and a valve that is healthy until an
onset drawn in the middle 60 % of the record and sticks from then on (data-driven or Karnopp friction, S 2–6 %,
with or without an actuator lag). Each loop is diagnosed with its nominal model (the linear part and the tuning,
an ideal valve) and as plant data (no model, OP declared as % travel).

The property asked for: the onset within 10 % of the record, S and J within 25 % and no finding besides the
valve's own (its friction, and an actuator lag where the loop has one) in at least 9 draws of 10. It is not met:
measured 1/20 with a model and 5/20 without (strict xfails below). What holds is checked at the rates measured
(seed 32): the change point locates the onset before any fit in 17 draws of 20; the answer is stiction in 14/20
with a model and 15/20 without; an onset it reports is within a tenth of the record in 6 of 7 with a model and 8
of 8 without; stiction from an onset within a tenth, with S within 25 %, in 5/20 and 7/20. What stands in the
way, measured: with a model the linear part re-fitted around the nominal chain leans on the controller's
correlation with a wandering load (its poles move several-fold faster than the nominal ones, and the valve
then lowers the fit: 6 no-stiction answers, extra dead-time, disturbance and characteristic findings); J is
underestimated where an actuator lag smooths the slip, and Karnopp friction's J is not Choudhury's J.

Time: about 4 minutes for the 20 draws, both ways (about 3 s a diagnosis on an idle core; 15–30 s on a machine
shared by six processes).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import pytest
from unseen_loops import LATE_ONSET, Draw, diagnosed, diagnosed_all, loop

from valve_emulator.diagnosis.explain.onset import suspect_onset

DRAWS = 20
SEED = 32
#: The tolerances of the property: the onset within this fraction of the record, S and J within this fraction.
ONSET_TOL, SIZE_TOL = 0.10, 0.25


def _loop(i: int) -> tuple:
    return loop("late_onset", (SEED, i))


@dataclass(frozen=True)
class Outcome:
    """One diagnosis against the loop's truth."""

    answer: str
    onset_err: float | None   # |reported − true onset| / record length; None when no onset is reported
    S_err: float | None       # relative errors of the friction's S and J in % travel; None without friction
    J_err: float | None
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
        J_err = abs(travel["J"]["value"] - truth["J"]) / truth["J"]
    return Outcome(answer=doc["answer"], onset_err=abs(onsets[0] - truth["onset"]) / length if onsets else None,
                   S_err=S_err, J_err=J_err, extra=tuple(f["physics"] for f in findings if f["physics"] not in own))


def _outcomes(mode: str) -> list[Outcome]:
    """Every draw's outcome in ``mode``; the diagnoses shared with the other property tests (and workers)."""
    diagnosed_all(key for key in LATE_ONSET if key.mode == mode)
    return [_outcome(i, mode) for i in range(DRAWS)]


def _count(mode: str, test) -> int:
    return sum(bool(test(o)) for o in _outcomes(mode))


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
@pytest.mark.parametrize(("mode", "least"), [("model", 6), ("plant", 8)])
def test_an_onset_the_answer_reports_is_within_a_tenth_of_the_record(mode, least):
    """Measured: 6 of 7 reported onsets with a model (the miss is the change point's: 900 s for 1679 s), 8 of 8
    without."""
    reported = [o.onset_err for o in _outcomes(mode) if o.onset_err is not None]
    assert sum(e <= ONSET_TOL for e in reported) >= least
    assert sum(e > ONSET_TOL for e in reported) <= 1


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 5), ("plant", 7)])
def test_stiction_is_found_from_its_onset_with_its_band_at_the_rate_reached(mode, least):
    """The part of the property the search reaches: the answer is stiction, from an onset within a tenth of the
    record, with S within 25 % (J and the other findings are left to the strict xfail below)."""
    reached = _count(mode, lambda o: o.answer == "stiction" and o.onset_err is not None and o.onset_err <= ONSET_TOL
                     and o.S_err is not None and o.S_err <= SIZE_TOL)
    assert reached >= least


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured 1/20 with a model and 5/20 without (see the module docstring)")
@pytest.mark.parametrize("mode", ["model", "plant"])
def test_onset_and_size_within_tolerance_and_nothing_else_in_nine_draws_of_ten(mode):
    assert _count(mode, lambda o: o.holds) >= 0.9 * DRAWS
