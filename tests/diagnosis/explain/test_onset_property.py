"""A valve that starts to stick part-way, on loops the search did not make.

The loops are the independent simulator's ``late_onset`` family (:mod:`valve_emulator.benchmark.independent`):
a level or a self-regulating plant, a PI one sample late, a wandering load, and a valve that is healthy until an
onset drawn in the middle 60 % of the record and sticks from then on (data-driven or Karnopp friction, S 2–6 %,
with or without an actuator lag). Each loop is diagnosed with its nominal model (the linear part and the tuning,
an ideal valve) and as plant data (no model, OP declared as % travel).

The property asked for: the onset within 10 % of the record, S and J within 25 % and no finding besides the
valve's own (its friction, and an actuator lag where the loop has one) in at least 9 draws of 10. J is judged
against the Js the drawn valve may be said to have (:func:`j_error`): its drawn J, and the J of every 2005 valve
that reproduces its own stem travel about as well as the best one (:func:`j_2005_range`) — on Karnopp stems the
stem's travel leaves J undetermined (J = 0 does about as well in 5 draws of 20). It is not met: measured 12/20
with a model and 13/20 as plant data (strict xfails below; 11/20 with a model before the findings were refined
again around the nominal gain before its test, 12/20 as plant data before a dead time far beyond the
healthy part's was searched again below it, 9/20 both ways before physics beside a late valve had to fit the
healthy part before its onset no worse). What holds is checked at the rates measured (seed 32), one
draw of slack each: the change point locates the onset before any fit in 17 draws of 20; the answer is stiction
in 16/20 with a model (19/20 before three weak calls became ``cannot_tell``, see below) and 18/20 without; an
onset it reports is within a tenth of the record in 15 of 16 with a model and 17 of 18 without; stiction from an
onset within a tenth, with S within 25 %, in 14/20 with a model (15/20 before) and 14/20 without (12/20 before
the dead-time cap); the whole property in 12/20 and 13/20. What stands in the way, measured (a draw may miss
for several reasons; with a model / without): not ``stiction`` (4 / 2: with a model three ``cannot_tell`` calls
on loops whose band OP's swings hardly cross and a level loop whose late fits settle on a band below a
twentieth of OP's span; without one two loops where no change point is located), hence no onset (4 / 2);
extra findings (3 / 1: with a model a dead time standing in for the valve's own actuator lag, and a dead time
beside a ``no_stiction`` and beside a ``cannot_tell`` answer; without one the plant's second lag as an actuator
lag); S off by more than 25 % (1 / 3; without a model two of them level loops identified with a dead time of 17
and 35 s for 0.3 and 1.1 s behind a lag, where the set point moves too seldom before the change point to
identify the healthy part); J off the range (2 / 2; 3 with a model before the findings were refined around the
nominal gain, draw 6); the onset a fifth of the record early (1 / 1).

What the recordings can show (:func:`shows`: each draw run again with its valve healthy throughout): the friction
shows within 0.005–0.059 of the record after the drawn onset in every draw, so the onset clause excludes none;
the drawn stem reverses after the onset at least three times in 18 draws, once in draw 1 and never in draw 2,
where S is not in the record — 18/20, the target itself, is the property's ceiling. Draw 14's extra dead time
is the valve's own one-sample lag, which the record does not tell from a dead time
(:func:`test_an_actuator_lag_of_one_sample_on_an_integrator_is_not_told_from_a_dead_time`).

The ``cannot_tell`` answers (draws 1, 2, 3 with a model, draw 1 as plant data; 2026-11-28) withhold calls that
would not hold if made (:func:`test_a_late_valve_answered_cannot_tell_would_not_have_met_the_property_as_a_call`):
the answer's rule for a band the record does not show costs the property nothing, and with draws 1 and 2 at the
ceiling, 18 asks every other draw to hold (``docs/diagnosis.md``, *The misses traced by class*).

Draws 15 and 3 traced to their records (2026-11-28, onset16; ``docs/diagnosis.md``, *Late onsets: where the onset is
located too early, and the slip it misses*): draw 15's change point is early because its loop, run again with the
valve healthy, errs as much before the drawn onset as the sticky loop after it
(:func:`test_draw_15s_healthy_loop_errs_as_much_before_its_onset_as_the_sticky_loop_after_it`; located right, its
size still misses both ways), and at draw 3's exact linear part and onset the free run does not tell its slip
(:func:`test_draw_3s_record_does_not_size_its_slip_at_the_exact_linear_part_in_free_run`).

Time: about 4 minutes for the 20 draws, both ways (about 3 s a diagnosis on an idle core; 15–30 s on a machine
shared by six processes).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, replace

import numpy as np
import pytest
from unseen_loops import LATE_ONSET, Draw, diagnosed, diagnosed_all, loop

import valve_emulator as ve
from valve_emulator.benchmark.independent import draw_loop, nominal_mapping, simulate
from valve_emulator.config import loop_from_mapping
from valve_emulator.diagnosis.explain.locate import turning_points
from valve_emulator.diagnosis.explain.onset import BLOCKS, MIN_RISE, suspect_onset
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.physics.actuator import actuator_response
from valve_emulator.physics.stiction import simulate_many

DRAWS = 20
SEED = 32
#: The tolerances of the property: the onset within this fraction of the record, S and J within this fraction.
ONSET_TOL, SIZE_TOL = 0.10, 0.25
#: A 2005 valve reproduces a drawn valve's stem about as well as the best one when its RMS is within this
#: fraction of the best's (:func:`j_2005_range`; the property holds in 9/20 draws both ways at 5 % as at 10 %,
#: in 10/20 with a model and 9/20 without at 20 %).
AS_WELL = 0.10


def _loop(i: int) -> tuple:
    return loop("late_onset", (SEED, i))


#: A departure shows in the recording when it exceeds this many σ of the measurement's noise for :data:`SHOWS_FOR`
#: samples running (:func:`shows`).
SHOWS_SIGMA, SHOWS_FOR = 3.0, 5


def _first_run(mask: np.ndarray, run: int) -> int | None:
    """The first index of ``run`` True values in a row in ``mask``, or None."""
    count = 0
    for k, m in enumerate(mask):
        count = count + 1 if m else 0
        if count >= run:
            return k - run + 1
    return None


@functools.cache
def shows(i: int) -> tuple[float, int]:
    """When draw ``i``'s friction first shows in its recording, and how often its stem reverses after the onset.

    The same loop (its load and noise draws) run again with the valve healthy throughout
    (:func:`~valve_emulator.benchmark.independent.draw_loop`): the friction shows from the first sample where
    the sticky record's PV departs from the healthy one's by more than :data:`SHOWS_SIGMA` σ of PV's noise, or its
    OP from the healthy OP by as many σ of OP's sample-to-sample noise (measured on the healthy record), for
    :data:`SHOWS_FOR` samples running. Before that no method can tell the record from a healthy loop's.
    The reversals: turning points of the drawn stem's travel after the onset with a hysteresis of S/10 — S, the
    band a reversing OP must cross before the stem moves back, is in the data only where the stem reverses."""
    loop_, extra = draw_loop("late_onset", np.random.default_rng([SEED, i]))
    sticky, truth, _ = _loop(i)   # the draw's own recording: draw_loop's loop, simulated
    healthy, _ = simulate(replace(loop_, valve=replace(loop_.valve, onset=np.inf)))
    sigma_op = float(np.std(np.diff(healthy.op))) / np.sqrt(2.0)
    runs = [_first_run(np.abs(sticky.pv - healthy.pv) > SHOWS_SIGMA * loop_.measurement.noise, SHOWS_FOR),
            _first_run(np.abs(sticky.op - healthy.op) > SHOWS_SIGMA * sigma_op, SHOWS_FOR)]
    first = min(k for k in runs if k is not None)
    k0 = int(np.ceil(extra["onset"] / sticky.dt))
    return float(sticky.t[first]), int(turning_points(truth["mv"][k0:], 0.1 * truth["S"]).size)


def _stem_rms(op: np.ndarray, mv: np.ndarray, S: np.ndarray, J: np.ndarray) -> np.ndarray:
    """RMS (% travel) of each 2005 valve's (S, J) travel on ``op`` against the stem travel ``mv``, at its best
    initial direction and with the operating point free (a constant offset)."""
    out = []
    for direction in (1, -1):
        r = mv[:, None] - simulate_many(op, S, J, direction=direction)
        out.append(np.sqrt(np.mean((r - r.mean(axis=0)) ** 2, axis=0)))
    return np.minimum(*out)


@functools.cache
def _stem_fits(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (S, J) grid of 2005 valves (:mod:`valve_emulator.physics.stiction`, the model the diagnosis reports)
    and the RMS of each against draw ``i``'s own stem travel from its OP after the onset (:func:`_stem_rms`):
    no plant, no noise, the actuator lag applied to OP where it acts before the friction, OP taken as it is or
    one sample earlier (the better of the two)."""
    rec, truth, _ = _loop(i)
    valve = truth["valve"]
    k0 = int(np.ceil(truth["onset"] / rec.dt)) + 1
    op = np.clip(np.asarray(rec.op, dtype=float), 0.0, 100.0)
    if valve["actuator_lag"] > 0 and valve["order"] == "lag_first":
        op = actuator_response(op, valve["actuator_lag"], rec.dt)
    mv = np.asarray(truth["mv"], dtype=float)[k0:]
    S, J = (a.ravel() for a in np.meshgrid(truth["S"] * np.linspace(0.3, 2.0, 69),
                                           truth["S"] * np.linspace(0.0, 1.6, 41)))
    rms = np.minimum(*(_stem_rms(op[k0 - shift:op.size - shift], mv, S, J) for shift in (0, 1)))
    return S, J, rms


@functools.cache
def valve_2005(i: int) -> tuple[float, float]:
    """The (S, J) of the 2005 valve that best reproduces draw ``i``'s own stem travel (:func:`_stem_fits`).

    Why: the drawn valve is a Karnopp stem or a data-driven valve written from its definition, whose S and J
    are defined as the 2005 model's, but whose cycles differ in detail (a Karnopp stem re-sticks during slow
    motion, the data-driven one rests after 1.5 samples of a held input). Fitted to the valve's own OP→MV,
    the 2005 model reproduces S but not J: its J misses the drawn J by more than 25 % in 8 draws of 20
    (:func:`test_the_2005_valve_fitted_to_the_drawn_valve_alone_reproduces_its_S_but_not_always_its_J`)."""
    S, J, rms = _stem_fits(i)
    j = int(np.argmin(rms))
    return float(S[j]), float(J[j])


@functools.cache
def j_2005_range(i: int) -> tuple[float, float]:
    """The least and largest J of the 2005 valves (any S) that reproduce draw ``i``'s stem travel with an RMS
    within :data:`AS_WELL` of the best one's (:func:`_stem_fits`).

    Why a range: the best 2005 valve's RMS is the floor the model's mismatch sets, and where the stem's travel
    hardly depends on J that floor is met by very different Js: on 5 draws of 20 a 2005 valve with J = 0
    reproduces the stem within a tenth of the best (four Karnopp stems and one data-driven valve of J/S = 0.2),
    and on 5 the range is wider than the ±25 % the property allows
    (:func:`test_the_stem_travel_leaves_the_2005_J_undetermined_in_a_quarter_of_the_draws`): a single best J
    is then an accident of the grid, not a truth to judge a diagnosis by."""
    _, J, rms = _stem_fits(i)
    near = J[rms <= (1.0 + AS_WELL) * rms.min()]
    return float(near.min()), float(near.max())


def _j_scale(i: int) -> float:
    """The scale J errors of draw ``i`` are measured on: the larger of the best 2005 J and the drawn J."""
    return max(valve_2005(i)[1], _loop(i)[1]["J"])


def j_error(J: float, i: int) -> float:
    """Distance of a diagnosed J from the Js draw ``i``'s valve may be said to have — the drawn J, and the
    range of 2005 valves that reproduce its stem about as well as the best (:func:`j_2005_range`), and anything
    between — relative to :func:`_j_scale` (a valve whose best 2005 J is 0 is judged on the drawn J's scale)."""
    lo, hi = j_2005_range(i)
    J_drawn = _loop(i)[1]["J"]
    lo, hi = min(lo, J_drawn), max(hi, J_drawn)
    return max(lo - J, J - hi, 0.0) / _j_scale(i)


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
def test_the_stem_travel_leaves_the_2005_J_undetermined_in_a_quarter_of_the_draws():
    """Why J is judged against a range (:func:`j_2005_range`): 2005 valves that reproduce the drawn valve's own
    stem travel within a tenth of the best one's RMS have Js spread wider than the ±25 % the property allows in
    5 draws of 20 (four Karnopp stems), and one with J = 0 among them in 5; in 13 draws the range lies within
    the best J ± 25 %, and there the range and the best J judge alike."""
    ranges = [j_2005_range(i) for i in range(DRAWS)]
    wide = sum(hi - lo > 2 * SIZE_TOL * _j_scale(i) for i, (lo, hi) in enumerate(ranges))
    zero = sum(lo == 0.0 for lo, _ in ranges)
    tight = sum(valve_2005(i)[1] * (1 - SIZE_TOL) <= lo and hi <= valve_2005(i)[1] * (1 + SIZE_TOL)
                for i, (lo, hi) in enumerate(ranges))
    assert 4 <= wide <= 6
    assert zero >= 4
    assert tight >= 12


@pytest.mark.slow
def test_the_drawn_onset_shows_within_a_tenth_of_the_record_and_the_stem_reverses_after_it_in_all_but_two():
    """What the recording can show of the property's two clauses (:func:`shows`; one test, so that the 20 healthy
    re-runs are simulated once).

    The onset: the friction never shows before its drawn onset, and shows within a tenth of the record after
    it in all 20 draws — measured 0.005–0.059 of the record after (20–177 s of 3000; the latest, draw 18, an
    actuator lag before a valve of S 2.1 %). So the onset's tolerance excludes no draw.

    The size: the drawn stem reverses after the onset 3–67 times in 18 draws of 20, once in draw 1 and never in
    draw 2 (a data-driven valve sticking from 71 % and 80 % of the record, its stem moving one way only): there
    S is shown once or not at all, and a diagnosis that meets the property's S clause there meets it by luck.
    18/20 is the property's ceiling for the size."""
    late = []
    for i in range(DRAWS):
        rec, truth, _ = _loop(i)
        first, _ = shows(i)
        assert first >= truth["onset"]
        late.append((first - truth["onset"]) / (rec.t[-1] - rec.t[0]))
    assert max(late) <= ONSET_TOL
    few = [i for i in range(DRAWS) if shows(i)[1] < 2]
    assert len(few) <= 2


@pytest.mark.slow
def test_an_actuator_lag_of_one_sample_on_an_integrator_is_not_told_from_a_dead_time():
    """Why draw 14 misses with its model (an extra dead time of 1.2 s for 0.32 s, beside the valve's own 0.97 s
    actuator lag, dt = 1 s, a pure integrator): on the draw's own loop run open-loop on its recorded OP, with
    neither load nor friction, both the actuator lag (τ 0.90 s) and a dead time (1.23 s) explain PV by a ΔBIC of
    about 480, less than a finding's threshold apart (measured 3). The record cannot say which of the two the
    valve's lag is; the property counts the dead time as an extra finding."""
    loop_, _ = draw_loop("late_onset", np.random.default_rng([SEED, 14]))
    healthy = replace(loop_, valve=replace(loop_.valve, onset=np.inf))
    closed, _ = simulate(healthy)
    rec, _ = simulate(replace(healthy, manual_op=tuple(closed.op), load=()))
    d = ve.diagnose(rec, loop_from_mapping(nominal_mapping(loop_, "late_onset")))
    first = {r.option: r.delta_bic for r in d.explanation.ranking if r.round == 1}
    assert first["actuator_lag"] >= DELTA_BIC and first["dead_time"] >= DELTA_BIC
    assert abs(first["actuator_lag"] - first["dead_time"]) < DELTA_BIC


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "since 2026-11-28 a level loop's integrating model is held and each round judged under the drifting-load "
    "noise model (docs/diagnosis.md, *A level loop's model is held*): draw 10's late valve is sized right (S 3 % "
    "off, J exact) and its gain held, but no onset is located, so the property does not hold there"))
def test_a_late_valve_is_sized_around_the_nominal_gain_when_the_gain_moves_only_for_the_free_run():
    """Draw 10 with its model (a Karnopp stem of S 4.33 % from 1187 s on a level loop, a 3.1 s lag): the
    search's gain was 0.43 of the nominal one, and around it the late valve's band S 2.39 %. The gain moved for
    a ΔBIC of 1,989 against the nominal gain with that same band (the grid of the refinement around the held
    gain fitted the gain freely; now at that gain, :func:`~valve_emulator.diagnosis.fit.linear.input_grid_sse`).
    Held, and the late valve searched afresh there (:func:`~valve_emulator.diagnosis.explain.onset.late_afresh`),
    the band is within a quarter of the drawn S, and under the drifting-load noise model the moved gain no longer counts
    (it must beat the held one there too, where a finding starts late): measured S 4.03, J 0.50 (drawn 0.93, the stem's
    2005 Js reach 0), from 1016 s (+0.057 of the record), the gain held."""
    o = _outcome(10, "model")
    assert o.holds, o
    moved = {m["parameter"]: m["moved"] for m in diagnosed(Draw("late_onset", (SEED, 10), "model")).doc["linear_part"]}
    assert moved["gain"] is False


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
@pytest.mark.parametrize(("mode", "least", "wrong"), [("model", 14, 2), ("plant", 16, 2)])
def test_an_onset_the_answer_reports_is_within_a_tenth_of_the_record(mode, least, wrong):
    """Measured: 15 of 16 reported onsets with a model, 17 of 18 without. The miss: the change point's (about
    1090 s for 1679 s, both ways)."""
    reported = [o.onset_err for o in _outcomes(mode) if o.onset_err is not None]
    assert sum(e <= ONSET_TOL for e in reported) >= least
    assert sum(e > ONSET_TOL for e in reported) <= wrong


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 15), ("plant", 17)])
def test_a_valve_that_starts_to_stick_part_way_is_answered_stiction(mode, least):
    """Measured 16/20 with a model, 18/20 without: a valve that starts late counts where the free run alone would
    not let it (under the drifting-load noise model,
    :meth:`~valve_emulator.diagnosis.explain.search.Search.late_counts`). With a model 19/20 before the answer
    with a model went through plant data's rule for a band the record does not show: three weak calls on loops
    that do not cycle, whose band OP's swings hardly cross, are ``cannot_tell`` (``docs/diagnosis.md``)."""
    assert _count(mode, lambda o: o.answer == "stiction") >= least


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 14), ("plant", 13)])
def test_stiction_is_found_from_its_onset_with_its_band_at_the_rate_reached(mode, least):
    """The part of the property the search reaches: the answer is stiction, from an onset within a tenth of the
    record, with S within 25 % (J and the other findings are left to the strict xfail below). Measured 15/20 with
    a model (14/20 before a late valve was searched afresh around the nominal gain, draw 10, and 15/20 before
    32.3's weak call became ``cannot_tell``), 14/20 without (12/20 before a dead time far
    beyond the healthy part's was searched again below it,
    :func:`~valve_emulator.diagnosis.explain.onset.delay_cap`)."""
    reached = _count(mode, lambda o: o.answer == "stiction" and o.onset_err is not None and o.onset_err <= ONSET_TOL
                     and o.S_err is not None and o.S_err <= SIZE_TOL)
    assert reached >= least


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "least"), [("model", 12), ("plant", 12)])
def test_onset_size_and_nothing_else_at_the_rate_reached(mode, least):
    """The whole property, at the rate the search reaches: measured 12/20 with a model and 13/20 without (J
    judged against the drawn J and the 2005 range, :func:`j_error`; with a model 13/20 before a level loop's
    integrating plant was held (2026-11-28: draw 10 then locates no onset, docs/diagnosis.md *A level loop's model
    is held*), 12/20 before the grid of the
    refinement around the nominal gain held that gain and a late valve was searched afresh there — draws 0 and
    10 hold, draw 8 misses on J, 1.80 for 2.69–2.87 at the nominal gain; 11/20 with a model before the findings were
    refined again around the nominal gain before its test, :mod:`~valve_emulator.diagnosis.explain.prior`;
    12/20 without before the dead-time cap)."""
    assert _count(mode, lambda o: o.holds) >= least


#: The valve a ``cannot_tell`` answer withholds, as its first reason names it (``decision._claimed_valve``): S, and J
#: where the valve is a sticky one (a deadband's J is 0), in OP's units — % travel on these draws.
WITHHELD = re.compile(r"S ≈ ([0-9.eE+-]+) %(?:, J ≈ ([0-9.eE+-]+) %)?")


def withheld(doc: dict) -> tuple[float, float]:
    """S and J of the valve a ``cannot_tell`` document names first (:data:`WITHHELD`)."""
    found = WITHHELD.search(doc["reasons"][0]["sentence"])
    assert doc["reasons"][0]["code"] in ("stiction", "deadband") and found, doc["reasons"][0]
    return float(found.group(1)), float(found.group(2) or 0.0)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["model", "plant"])
def test_a_late_valve_answered_cannot_tell_would_not_have_met_the_property_as_a_call(mode):
    """What the answer's rule for a band the record does not show costs the property: nothing. Every draw it turns
    to ``cannot_tell`` withholds a valve sized off the drawn one by more than the property allows (S or J beyond
    25 %), or one whose drawn stem reverses fewer than twice after its onset, where the record holds no S to size
    (:func:`shows`). Measured (2026-11-28, main ec88b64's shared draws): with a model draws 1, 2 and 3 (S 2.39 for
    4.68; a deadband of S 1.41 for 4.02, beside an actuator lag and a dead time; J 0.366 for the stem's 1.33), as
    plant data draw 1 (a deadband of S 4.38 for 4.68, J 0 for 2.25–3.56, and no onset); draws 1 and 2 are the two
    whose stem reverses once and never. Made calls, none of them would hold: the property's misses lie elsewhere."""
    outcomes = _outcomes(mode)
    withheld_here = [i for i, o in enumerate(outcomes) if o.answer == "cannot_tell"]
    for i in withheld_here:
        S, J = withheld(diagnosed(Draw("late_onset", (SEED, i), mode)).doc)
        truth = _loop(i)[1]
        sized = abs(S - truth["S"]) <= SIZE_TOL * truth["S"] and j_error(J, i) <= SIZE_TOL
        assert not sized or shows(i)[1] < 2, (i, S, J)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured 12/20 with a model, 13/20 without (see the module docstring)")
@pytest.mark.parametrize("mode", ["model", "plant"])
def test_onset_and_size_within_tolerance_and_nothing_else_in_nine_draws_of_ten(mode):
    assert _count(mode, lambda o: o.holds) >= 0.9 * DRAWS


def _error_rms(rec, lo: int, hi: int | None = None) -> float:
    """RMS of the control error SP − PV of ``rec`` on samples ``lo:hi``."""
    e = (np.asarray(rec.sp, dtype=float) - np.asarray(rec.pv, dtype=float))[lo:hi]
    return float(np.sqrt(np.mean(e * e)))


@pytest.mark.slow
def test_draw_15s_healthy_loop_errs_as_much_before_its_onset_as_the_sticky_loop_after_it():
    """Why draw 15's onset is located a fifth of the record early, both ways (a Karnopp stem from 1679 s on an
    integrating loop; the change point at 900 s, the answers' onsets 1061 and 1080 s). The same loop run with its
    valve healthy throughout (its load and noise draws kept) has a control error of RMS 0.92 from the change point
    to the drawn onset — a set-point step of +3.0 at 1004 s, the record's largest, and the load's deepest
    excursion near 1300 s — against 0.50 before the change point and 0.87 in the sticky record after the onset.
    So the energy of the control error does not step up at the onset (its log rises 0.40 there from the part
    after the change point, :data:`~valve_emulator.diagnosis.explain.onset.MIN_RISE` is 1.0); the healthy
    record alone locates no change point. The record shows the friction from 1740 s (:func:`shows`), in the shape
    of OP and PV, not in the size of the control error. Measured 2026-11-28 (onset16)."""
    rec, truth, _ = _loop(15)
    loop_, _ = draw_loop("late_onset", np.random.default_rng([SEED, 15]))
    healthy, _ = simulate(replace(loop_, valve=replace(loop_.valve, onset=np.inf)))
    found = suspect_onset(rec.pv, rec.sp)
    k0 = int(np.ceil(truth["onset"] / rec.dt))
    assert found is not None and k0 - found.sample > ONSET_TOL * rec.t.size   # located more than a tenth early
    assert suspect_onset(healthy.pv, healthy.sp) is None
    assert _error_rms(healthy, found.sample, k0) >= _error_rms(rec, k0)
    assert _error_rms(healthy, found.sample, k0) >= 1.5 * _error_rms(healthy, 0, found.sample)
    w = rec.t.size // BLOCKS
    logs = np.log(np.mean(((rec.sp - rec.pv)[:BLOCKS * w] ** 2).reshape(BLOCKS, w), axis=1))
    rise = logs[int(np.ceil(k0 / w)):].mean() - logs[found.sample // w:k0 // w].mean()
    assert rise < 0.5 * MIN_RISE


@pytest.mark.slow
def test_draw_3s_record_does_not_size_its_slip_at_the_exact_linear_part_in_free_run():
    """Why draw 3 with its model withholds a valve of J 0.37 % for the stem's 1.33 (a data-driven valve — the 2005
    model itself — of S 2.08, J 1.29 from 2009 s on a second-order loop with dead time, its nominal model exact).
    The recorded OP run through the draw's own valve and plant (the independent simulator, open loop), without the
    load the diagnosis must take as a disturbance, from the drawn onset: PV after the onset is fitted with a
    residual of RMS 0.32, more than five times PV's noise (0.057), and a valve of a third of the drawn slip
    (S 2.6, J 0.37, the withheld one) fits it better (0.30). The free run — the search's cost — does not tell the
    slip here, at the true linear part and onset; a grid of S 1.8–2.9 and J 0.2–1.6 scores 0.30–0.47 with no
    single valley (docs/diagnosis.md, *Late onsets: where the onset is located too early, and the slip it
    misses*). Measured 2026-11-28 (onset16)."""
    rec, truth, _ = _loop(3)
    loop_, _ = draw_loop("late_onset", np.random.default_rng([SEED, 3]))
    assert loop_.valve.friction == "data_driven"
    k0 = int(np.ceil(truth["onset"] / rec.dt))
    base = replace(loop_, manual_op=tuple(rec.op), load=())

    def rms(S: float, J: float) -> float:
        r, _ = simulate(replace(base, valve=replace(loop_.valve, S=S, J=J)))
        d = (r.pv - rec.pv)[k0:]
        return float(np.std(d))

    drawn = rms(truth["S"], truth["J"])
    assert drawn > 5.0 * loop_.measurement.noise
    assert rms(1.25 * truth["S"], truth["J"] / 3.5) < drawn
