"""A band whose swallowed moves reach PV through the identified plant with strong evidence (ΔBIC ≥
``decision.LEAK_BIC``, Kass & Raftery's "strong"), not only very strong evidence (``DELTA_BIC``), is a band the record
does not show (``decision.band_leaks``; heal19, 2026-11-28). Known truth: a level (an integrating plant) under a
random-walk load, its PV measured with much noise (σ 1, so that what leaks shows only weakly), fed through a valve
that is either healthy or holds OP's moves inside a real dead band S = 3 %. The band asked about is the same in both.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from band_valve import level_through_band

from valve_emulator.diagnosis.assess import decision
from valve_emulator.diagnosis.assess.decision import LEAK_BIC, band_leaks
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.diagnosis.fit.load_check import Swallowed

DT = 1.0
S = 3.0
N = 2000
PV_NOISE = 1.0
SEEDS = range(20)


def _explained(seed: int, healthy: bool) -> SimpleNamespace:
    """An explained loop (traces, an identified integrating plant with a 2 s dead time) whose valve is healthy (PV
    integrates OP) or holds OP's moves inside the band (PV integrates the band's output)."""
    pv, op, claimed = level_through_band(seed, healthy, S, N, DT, noise=PV_NOISE)
    traces = SimpleNamespace(t=np.arange(N) * DT, pv=pv, op=op, mv_after=claimed)
    return SimpleNamespace(traces=traces, plant={"gain": 0.03, "taus": [], "integrating": True, "delay": 2.0})


BAND = Finding(physics="deadband", parameters={"S": S, "J": 0.0}, windows=(), evidence="", description="",
               intervals={"S": (2.5, 3.5)}, load_delta_bic=50.0)


def test_the_threshold_is_evidence_below_a_candidates():
    assert 0.0 < LEAK_BIC < DELTA_BIC


def test_a_healthy_valve_s_weak_leak_is_found():
    """Fails on main (ΔBIC ≥ 10 asked): there the leak is found on 11 of these 20 healthy loops (measured), here on
    18. At least 16 asked."""
    found = [band_leaks(_explained(seed, healthy=True), BAND) for seed in SEEDS]
    assert sum(leak is not None for leak in found) >= 16, found
    assert all(leak.delta_bic >= LEAK_BIC and leak.share > 0.0 for leak in found if leak is not None)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_stuck_valve_s_band_is_shown(seed):
    """The other side of the lower threshold, on the same noisy record: a valve that really holds its band leaks
    nothing (none of 40 seeds reached ΔBIC 2, measured: at most −4.4), at the lower threshold as at the higher."""
    assert band_leaks(_explained(seed, healthy=False), BAND) is None


@pytest.mark.parametrize(("through_plant", "through_integrator", "named"), [
    (7.0, 700.0, "integrator"),     # the strong leak through the plant must not stand for the very strong one
    (50.0, 20.0, "plant"),
])
def test_the_strongest_leak_found_is_the_one_named(monkeypatch, through_plant, through_integrator, named):
    """Where the swallowed moves reach PV both through the identified self-regulating plant (ΔBIC ≥ ``LEAK_BIC``)
    and through the integrator it is over short times (ΔBIC ≥ ``DELTA_BIC``, the gain its K/τ), the answer's reason
    names the stronger. Only the regressions are stood in for (their ΔBIC given); the plant, the settling start and
    the short-time slope are the decision's own. Before, the plant's leak was named whenever it held: healthy level
    loops whose reason cited ΔBIC 717 through the integrator cited 6.6 once the plant's threshold was lowered."""
    tau, gain = 20.0, 0.6
    explained = _explained(0, healthy=True)
    explained.plant = {"gain": gain, "taus": [tau], "integrating": False, "delay": 2.0}

    def regressions(pv, op, valve, structure, dt, start):
        if structure.integrating:     # the valve alone explains less than through the plant: the slope's case
            return Swallowed(bic_valve=1000.0, bic_leaking=1000.0 - through_integrator, share=0.6, gain=gain / tau)
        return Swallowed(bic_valve=100.0, bic_leaking=100.0 - through_plant, share=0.2)

    monkeypatch.setattr(decision, "swallowed", regressions)
    leak = band_leaks(explained, BAND)
    assert leak is not None
    assert leak.delta_bic == max(through_plant, through_integrator)
    assert (leak.slope is not None) == (named == "integrator")
    assert leak.held == (named == "integrator")
