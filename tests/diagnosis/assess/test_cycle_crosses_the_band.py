"""A regular cycle speaks for a valve band only when OP's swing in it crosses the band (``decision.cycle_crosses``).

A sticky valve under a PI makes a limit cycle by sticking until OP has crossed its band and slipping; by the
stiction model's describing function a valve whose OP swings by less than S does not move at all (Choudhury,
Thornhill & Shah 2005). So a strong call, which asks for a regular cycle, asks that the cycle's OP swing reach
``CYCLE_CROSSING`` (√(2/3), a triangle's swing read as a sine's) of the band's lower 95 % bound.

Known truth: the independent simulator's sticky level loops (``tests/unseen_loops.py: LEVEL``) that cycle cross their
true band (measured 2026-11-28: 34 of 34, OP's swing 1.0–3.2 times S); the unit tests build the cycle by hand.
"""

from __future__ import annotations

import numpy as np
from unseen_loops import LEVEL, loop

from valve_emulator.diagnosis.answers import Reason, Strength
from valve_emulator.diagnosis.assess.adequacy import adequacy
from valve_emulator.diagnosis.assess.decision import (
    CYCLE_CROSSING,
    _stiction,
    cycle_crosses,
    strength_with_model,
)
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.fit.frame import Frame
from valve_emulator.recordings.recording import Recording

RNG = np.random.default_rng(3)


def _cycling(op_swing: float, period: float = 120.0, n: int = 2400) -> Recording:
    """A loop cycling regularly: OP a triangle wave swinging ``op_swing`` peak to peak (a stick-slip cycle's OP under
    integral action), PV lagging it, a little noise on both."""
    t = np.arange(n, dtype=float)
    phase = (t / period) % 1.0
    tri = 2.0 * np.abs(2.0 * phase - 1.0) - 1.0          # −1 … 1
    op = 50.0 + 0.5 * op_swing * tri + 0.02 * RNG.normal(size=n)
    pv = 10.0 + np.sin(2 * np.pi * t / period - 1.2) + 0.02 * RNG.normal(size=n)
    return Recording(t=t, sp=np.full(n, 10.0), op=op, mv=None, pv=pv, source="cycle")


def _band(S: float, low: float | None = None) -> Finding:
    low = S if low is None else low
    return Finding(physics="stiction", parameters={"S": S, "J": 0.5}, windows=(), evidence="", description="",
                   intervals={"S": (low, S * 1.05), "J": (0.2, 0.8)}, fit_without=10.0, fit_with=90.0,
                   load_delta_bic=60.0)


def test_a_cycle_whose_op_swing_crosses_the_band_speaks_for_it_and_one_inside_it_does_not():
    rec = _cycling(op_swing=3.0)
    facts = adequacy(rec).facts
    assert facts["oscillating"]
    assert cycle_crosses(rec.op, facts, rec.dt, _band(2.85))                      # a triangle just across the band
    assert not cycle_crosses(rec.op, facts, rec.dt, _band(3.3))                   # ... and one just inside it
    assert cycle_crosses(rec.op, facts, rec.dt, _band(3.3 * CYCLE_CROSSING))      # read as a sine, it crosses that
    assert not cycle_crosses(rec.op, facts, rec.dt, _band(6.0, low=5.5))          # twice the swing: not its cycle
    assert cycle_crosses(rec.op, facts, rec.dt, _band(6.0, low=2.5))              # unless the interval reaches in


def test_with_a_model_a_call_on_a_cycle_inside_its_band_is_weak():
    """Everything else a strong call asks for holds (40 points of fit bought, a regular cycle, ΔBIC 60 under the
    drifting-load model): main called both strong."""
    rec = _cycling(op_swing=2.0)
    facts = adequacy(rec).facts
    assert strength_with_model(_band(1.8), facts, 50.0, 90.0, rec) is Strength.STRONG
    assert strength_with_model(_band(4.6), facts, 50.0, 90.0, rec) is Strength.WEAK


def test_as_plant_data_a_call_on_a_cycle_inside_its_band_says_why_it_is_weak():
    rec = _cycling(op_swing=2.0)
    ad = adequacy(rec)
    frame = Frame.travel_percent()
    crossed = _stiction(_band(1.8), 1.8, "fits", frame, ad, rec.op, rec.dt)
    inside = _stiction(_band(4.6), 4.6, "fits", frame, ad, rec.op, rec.dt)
    assert Reason.WEAK_EVIDENCE not in {code for code, _ in crossed.reasons}
    weak = [text for code, text in inside.reasons if code is Reason.WEAK_EVIDENCE]
    assert len(weak) == 1 and "not the band's" in weak[0] and "peak to peak" in weak[0], inside.reasons


def test_a_sticky_level_loops_limit_cycle_crosses_its_true_band():
    """The rule's premise on known truth: every sticky level loop of ``LEVEL`` that cycles regularly crosses the
    band it was simulated with (no diagnosis: the simulated loops only). Most of them cycle (34 of 40, measured
    2026-11-28), so the premise is asked of enough loops to fail."""
    cycling, inside = [], []
    for key in LEVEL:
        rec, truth, _ = loop(key.family, key.entropy)
        facts = adequacy(rec).facts
        if not facts["oscillating"]:
            continue
        cycling.append(key.name)
        S = truth["S"]
        true_band = Finding(physics="stiction", parameters={"S": S, "J": truth["J"]}, windows=(), evidence="",
                            description="", intervals={"S": (S, S)})
        if not cycle_crosses(rec.op, facts, rec.dt, true_band):
            inside.append((key.name, S))
    assert len(cycling) >= 30, cycling
    assert not inside, inside
