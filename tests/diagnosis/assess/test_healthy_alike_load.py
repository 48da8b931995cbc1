"""A stiction call on a loop that does not cycle, whose band the record does not show, and which a linear valve
with a slowly drifting load explains at least as well, is no call: ``cannot_tell``, naming the sticky valve and the
healthy one (``decision._healthy_alike``, the drifting-load reading beside the band OP hardly crosses; heal18,
2026-11-28). Either healthy reading alone, or both without the unshown band, leaves the call standing.

A level (an integrating plant) under a random-walk load, fed through a valve with a real dead band S = 3 % whose OP
crosses the band often (a random walk far wider than S); the band finding is given a 95 % interval reaching into
OP's noise (the record does not tell it from no band), or one clear of it, and a drifting-load ΔBIC either side
of :data:`~valve_emulator.diagnosis.assess.decision.ALIKE_LOAD_BIC`.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from band_valve import held

from valve_emulator.diagnosis.answers import Answer
from valve_emulator.diagnosis.assess.decision import (
    ALIKE_LOAD_BIC,
    CROSSING_SHARE,
    NOISE_BANDS,
    _healthy_alike,
    band_crossings,
)
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.fit.frame import Frame

DT = 1.0
S = 3.0
N = 2000
NOISE = 0.1   # OP noise σ (% travel): 3 σ = 0.3
FRAME = Frame.travel_percent()
CLEAR = (2.5, 3.5)                       # a 95 % interval clear of OP's noise: the band is shown
INTO_NOISE = (0.5 * NOISE_BANDS * NOISE, 3.5)   # reaching below 3 OP noise σ: not shown


def _level(seed: int = 0) -> tuple[SimpleNamespace, SimpleNamespace]:
    """A recording (t, OP) and an explained loop (traces, identified integrating plant) whose valve really holds
    OP's moves inside the band S: PV integrates the band's output, delayed 2 s, plus a random-walk load and
    noise."""
    rng = np.random.default_rng(seed)
    op = 50 + np.cumsum(rng.normal(0, 0.4, N)) + rng.normal(0, 0.5, N)
    valve = held(op, S)
    load = np.cumsum(rng.normal(0, 0.01, N))
    pv = np.cumsum(0.03 * DT * np.concatenate([np.full(3, valve[0]), valve[:-3]])) + np.cumsum(load) * 0.01
    t = np.arange(N) * DT
    traces = SimpleNamespace(t=t, pv=pv + rng.normal(0, 0.05, N), op=op, mv_after=valve)
    d = SimpleNamespace(traces=traces, plant={"gain": 0.03, "taus": [], "integrating": True, "delay": 2.0})
    return SimpleNamespace(t=t, op=op), d


def _finding(interval: tuple[float, float], load: float) -> Finding:
    return Finding(physics="deadband", parameters={"S": S, "J": 0.0}, windows=(), evidence="", description="",
                   intervals={"S": interval}, load_delta_bic=load)


def _decide(interval: tuple[float, float], load: float, oscillating: bool = False):
    rec, d = _level()
    ad = SimpleNamespace(facts={"oscillating": oscillating})
    return _healthy_alike(rec, d, _finding(interval, load), S, "held-out fit 0 % → 50 %", FRAME, ad, NOISE)


def test_the_premise_op_crosses_the_band_here():
    """The band-crossing sign is absent on this loop, so what decides is the drifting-load reading."""
    rec, _ = _level()
    assert band_crossings(rec.op, S) >= CROSSING_SHARE


def test_a_drifting_load_as_good_and_a_band_not_shown_make_no_call():
    """Fails on main before heal18 (a call whose OP crosses its band stood however well the load explained it)."""
    decided = _decide(INTO_NOISE, ALIKE_LOAD_BIC - 5.0)
    assert decided is not None and decided.answer is Answer.CANNOT_TELL
    assert "a valve with a deadband" in decided.reason and "healthy valve" in decided.reason
    assert "drifting load" in decided.reason and "no band at all" in decided.reason


def test_either_sign_alone_leaves_the_call():
    assert _decide(INTO_NOISE, ALIKE_LOAD_BIC + 50.0) is None      # the valve explains better than the load
    assert _decide(CLEAR, ALIKE_LOAD_BIC - 5.0) is None             # the record shows the band


def test_a_loop_that_cycles_keeps_its_call():
    assert _decide(INTO_NOISE, ALIKE_LOAD_BIC - 5.0, oscillating=True) is None
