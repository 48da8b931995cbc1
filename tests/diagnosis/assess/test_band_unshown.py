"""Does the record show that a valve band holds? (``decision.band_unshown``, the second sign of the rule that takes
back a stiction call on a loop that does not cycle and whose band OP hardly crosses.)

A level (an integrating plant) under a random-walk load, fed through a valve with a real dead band: OP's moves inside
the band leave PV alone, so the band is shown — unless its 95 % interval reaches into OP's noise, or the friction
acts on too short a stretch of the record to ask.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from band_valve import held

from valve_emulator.diagnosis.assess.decision import NOISE_BANDS, band_unshown
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.fit.frame import Frame

DT = 1.0
S = 3.0


def _sticky_level(seed: int, n: int = 2000) -> SimpleNamespace:
    """An explained loop (traces and identified plant, as ``Explanation`` carries them) whose valve really holds
    OP's moves inside a band S: PV integrates the band's output, delayed 2 s, plus a random-walk load and noise."""
    rng = np.random.default_rng(seed)
    op = 50 + np.cumsum(rng.normal(0, 0.4, n)) + rng.normal(0, 0.5, n)
    valve = held(op, S)
    load = np.cumsum(rng.normal(0, 0.01, n))
    pv = np.cumsum(0.03 * DT * np.concatenate([np.full(3, valve[0]), valve[:-3]])) + np.cumsum(load) * 0.01
    traces = SimpleNamespace(t=np.arange(n) * DT, pv=pv + rng.normal(0, 0.05, n), op=op, mv_after=valve)
    return SimpleNamespace(traces=traces, plant={"gain": 0.03, "taus": [], "integrating": True, "delay": 2.0})


def _finding(interval: tuple[float, float], onset_s: float | None = None) -> Finding:
    onset = None if onset_s is None else SimpleNamespace(onset_s=onset_s)
    return Finding(physics="deadband", parameters={"S": S, "J": 0.0}, windows=(), evidence="", description="",
                   intervals={"S": interval}, onset=onset)


FRAME = Frame.travel_percent()
NOISE = 0.1   # OP noise σ (% travel): 3 σ = 0.3, well below the band


def test_a_band_that_holds_the_moves_inside_it_and_stands_clear_of_op_noise_is_shown():
    for seed in range(3):
        assert band_unshown(_sticky_level(seed), _finding((2.5, 3.5)), NOISE, FRAME) is None


def test_a_band_whose_interval_reaches_into_op_noise_is_not_shown():
    """The same band, its 95 % interval reaching below 3 OP noise σ: the record does not tell it from no band."""
    low = 0.5 * NOISE_BANDS * NOISE
    why = band_unshown(_sticky_level(0), _finding((low, 3.5)), NOISE, FRAME)
    assert why is not None and "no band at all" in why and f"{NOISE_BANDS:g} OP noise σ" in why


def test_a_friction_acting_on_too_short_a_stretch_to_test_is_not_shown():
    """A band fitted from 1950 s on in a record of 2000 samples: too few samples after it to ask whether OP's moves
    inside it leave PV alone; from 1000 s on, enough."""
    d = _sticky_level(0)
    why = band_unshown(d, _finding((2.5, 3.5), onset_s=1950.0), NOISE, FRAME)
    assert why is not None and "too short" in why
    assert band_unshown(d, _finding((2.5, 3.5), onset_s=1000.0), NOISE, FRAME) is None
