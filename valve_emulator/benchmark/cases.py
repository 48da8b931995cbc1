r"""Concealed test recordings with a known truth: the cases of ``valve-emulator prove``
(run and tabulated by :mod:`valve_emulator.benchmark.proof`).

Each :class:`Case` is a closed loop simulated by :func:`~valve_emulator.simulation.loop.simulate_loop` with one
piece of physics that its *nominal* model leaves out. What the diagnosis gets is concealed the way a plant
historian conceals it:

* closed loop (OP is correlated with the PV noise through the controller);
* only ``t, op, pv`` are kept (no valve position, no set point);
* PV measurement noise inside the loop, its standard deviation a stated fraction of the PV amplitude
  (half the 1st–99th percentile range of a noise-free run of the same loop);
* the first part of the run is cut, so the record starts mid-cycle.

The actuator lag is simulated as an extra first-order factor of the plant behind a linear valve, which is
the same system (a lag commutes with a linear valve and characteristic).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from valve_emulator.config import LoopConfig, loop_from_mapping
from valve_emulator.physics.signal_chain import DEFAULT_RANGEABILITY
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation.loop import simulate_loop

__all__ = ["Case", "CASES", "generate", "loop_mapping", "nominal_mapping", "setpoint_steps"]


@dataclass(frozen=True)
class Case:
    """One concealed recording.

    Attributes
    ----------
    name : short label.
    truth : the physics the nominal model leaves out, ``{physics: parameters}`` in the JSON vocabulary
        (empty for the control case).
    loop : mapping in the loop-config schema for the *true* loop (valve, plant, controller, simulation).
    nominal : overrides that turn the true loop into the nominal one, ``{"valve": {...}, "plant": {...}}``.
    noise : PV noise standard deviation as a fraction of the PV amplitude.
    lag : actuator lag τ (s) added to the true plant (0 = none).
    cut : seconds cut from the start of the run.
    """

    name: str
    truth: dict
    loop: dict
    nominal: dict = field(default_factory=dict)
    noise: float = 0.05
    lag: float = 0.0
    cut: float = 300.0


def loop_mapping(num, den, delay, kc, ti, *, S=0.0, J=0.0, dt=1.0, duration=3300.0, sp_steps=(), disturbance=None,
                 characteristic="linear", rangeability=DEFAULT_RANGEABILITY, bias=50.0, seed=1, noise=None,
                 name="case") -> dict:
    """A closed loop in the loop-config schema (what a YAML file holds): plant ``num/den`` with dead time
    ``delay`` (s), a PI controller ``kc``, ``ti`` (s) around OP ``bias`` stepping its set point at ``sp_steps``
    (``[(t, sp), ...]``; default one step to 1 at 10 s), a valve with stiction ``S``, ``J`` (% travel);
    ``noise``: PV measurement noise (standard deviation, PV units; default none)."""
    plant = {"num": list(num), "den": list(den), "delay": delay, "pv0": 0.0}
    if disturbance:
        plant["disturbance"] = disturbance
    if noise is not None:
        plant["noise"] = noise
    return {
        "name": name,
        "valve": {"S": S, "J": J, "characteristic": characteristic, "rangeability": rangeability},
        "plant": plant,
        "controller": {"kc": kc, "ti": ti, "sp": 0.0, "bias": bias,
                       "sp_steps": [list(s) for s in sp_steps] or [[10.0, 1.0]]},
        "simulation": {"dt": dt, "duration": duration, "seed": seed},
    }


def setpoint_steps(levels, period, start=100.0) -> list[tuple[float, float]]:
    """Set-point steps ``[(t, level), ...]``: ``levels`` one after the other, every ``period`` s from ``start``."""
    return [(start + i * period, float(v)) for i, v in enumerate(levels)]


_CONC = ([3.0], [10.0, 1.0], 10.0)     # Table 1 concentration loop of the 2003 paper, Kc 0.2, Ti 10 s

#: The proof table: every effect the diagnosis names, several plants, tunings and parameter values.
CASES: tuple[Case, ...] = (
    Case("stiction, undershoot", {"stiction": {"S": 5.0, "J": 2.0}},
         loop_mapping(*_CONC, 0.2, 10.0, S=5.0, J=2.0, duration=10300.0), {"valve": {"S": 0.0, "J": 0.0}}),
    Case("stiction, no offset", {"stiction": {"S": 3.0, "J": 3.0}},
         loop_mapping([1.5], [20.0, 1.0], 5.0, 0.6, 25.0, S=3.0, J=3.0, duration=5300.0),
         {"valve": {"S": 0.0, "J": 0.0}}),
    Case("stiction, overshoot", {"stiction": {"S": 5.0, "J": 7.0}},
         loop_mapping(*_CONC, 0.2, 10.0, S=5.0, J=7.0, duration=5300.0), {"valve": {"S": 0.0, "J": 0.0}}),
    Case("stiction, level loop", {"stiction": {"S": 3.0, "J": 1.5}},
         loop_mapping([1.0], [1.0, 0.0], 0.0, 0.4, 2.0, S=3.0, J=1.5, dt=0.2, duration=1260.0),
         {"valve": {"S": 0.0, "J": 0.0}}, cut=60.0),
    Case("pure deadband, level loop", {"deadband": {"S": 3.0}},
         loop_mapping([1.0], [1.0, 0.0], 0.0, 0.4, 2.0, S=3.0, J=0.0, dt=0.2, duration=1260.0),
         {"valve": {"S": 0.0, "J": 0.0}}, cut=60.0),
    Case("stiction + dead time off by 2 samples", {"stiction": {"S": 5.0, "J": 2.0}, "dead_time": {"theta": 12.0}},
         loop_mapping([3.0], [10.0, 1.0], 12.0, 0.2, 10.0, S=5.0, J=2.0, duration=5300.0),
         {"valve": {"S": 0.0, "J": 0.0}, "plant": {"delay": 10.0}}),
    Case("dead-time error", {"dead_time": {"theta": 8.0}},
         loop_mapping([1.5], [20.0, 1.0], 8.0, 0.8, 20.0, duration=4300.0,
               sp_steps=setpoint_steps([2, -2, 4, 0, -3, 1, 3, -1] * 3, 170.0)),
         {"plant": {"delay": 5.0}}, noise=0.03),
    Case("equal-percentage characteristic", {"characteristic": {"type": "equal_percentage", "R": 30.0}},
         loop_mapping([2.0], [15.0, 1.0], 3.0, 0.3, 15.0, duration=4300.0, characteristic="equal_percentage",
               rangeability=30.0, bias=30.0,
               sp_steps=setpoint_steps([-25, 25, -10, 40, -30, 10, 30, -20] * 3, 170.0)),
         {"valve": {"characteristic": "linear"}}, noise=0.02),
    Case("actuator lag", {"actuator_lag": {"tau": 4.0}},
         loop_mapping([1.0], [8.0, 1.0], 2.0, 1.5, 8.0, duration=4300.0,
               sp_steps=setpoint_steps([3, -3, 5, 0, -4, 2, 4, -1] * 3, 170.0)),
         {}, noise=0.03, lag=4.0),
    Case("control (nothing left out)", {},
         loop_mapping([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=4300.0,
               sp_steps=setpoint_steps([3, -3, 5, 0, -4, 2, 4, -1] * 3, 170.0)),
         {}, noise=0.03),
)

def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merge(base.get(key, {}), value) if isinstance(value, dict) else value
    return out


def _with_lag(loop: dict, lag: float) -> dict:
    if lag <= 0:
        return loop
    plant = dict(loop["plant"])
    plant["den"] = list(np.polymul(plant["den"], [lag, 1.0]))
    return {**loop, "plant": plant}


def nominal_mapping(case: Case) -> dict:
    """The configuration mapping of a case's nominal model (what a user would write in its YAML file)."""
    return {**_merge(case.loop, {**case.nominal, "simulation": dict(case.loop["simulation"])}), "name": "nominal"}


def generate(case: Case, *, duration: float | None = None, seed: int | None = None
             ) -> tuple[Recording, LoopConfig, LoopConfig]:
    """Simulate a case: returns (concealed recording, nominal config, true config).

    ``duration`` (s, before the cut) and ``seed`` override the case's own, e.g. for short test runs.
    """
    loop = _with_lag(case.loop, case.lag)
    sim = dict(loop["simulation"])
    if duration is not None:
        sim["duration"] = float(duration)
    if seed is not None:
        sim["seed"] = int(seed)
    loop = {**loop, "simulation": sim}
    clean = simulate_loop(loop_from_mapping(loop))
    k_cut = int(round(case.cut / clean.dt))
    lo, hi = np.percentile(clean.pv[k_cut:], [1.0, 99.0])
    noisy_loop = _merge(loop, {"plant": {"noise": case.noise * 0.5 * float(hi - lo)}})
    true_cfg = loop_from_mapping(noisy_loop)
    run = simulate_loop(true_cfg)
    rec = Recording(run.t[k_cut:] - run.t[k_cut], None, run.op[k_cut:], None, run.pv[k_cut:],
                    source=case.name)
    nominal_cfg = loop_from_mapping(_merge(case.loop, {**case.nominal, "simulation": sim}))
    return rec, dataclasses.replace(nominal_cfg, name="nominal"), true_cfg
