"""A training scenario (:mod:`valve_emulator.scenario.training`) played by the station, tick by tick.

Loaded with ``POST /api/scenario {"yaml": text}`` (or ``{"scenario": mapping}``): every malfunction in it is
checked against the device first (:func:`~valve_emulator.device.malfunctions.parse_malfunction`), so a bad
scenario is refused whole. ``start`` resets the evaluation (a new session), applies the scenario's limits,
and from then on the station calls :meth:`ScenarioRun.on_tick` after every tick: due events fire, and each
trigger is tested on its condition:

- ``pv_outside``: PV outside ``band`` for ``for`` simulated seconds without interruption;
- ``manual``: the trainee's action log has an accepted switch of the unit to manual since the start;
- ``acknowledged``: the trainee acknowledged an alarm of the unit since the start;
- ``since_malfunction``: ``after`` simulated seconds have passed since a malfunction on the unit.

A trigger fires once. Its action is a malfunction, a line for the instructor (``say``) or a hint released
to the trainee (which costs points in the score).
"""

from __future__ import annotations

from typing import Any

from valve_emulator.device.malfunctions import MalfunctionError, parse_malfunction
from valve_emulator.scenario.timeline import ScenarioError
from valve_emulator.scenario.training import Condition, TrainingScenario, parse_training
from valve_emulator.station.core import StationError

__all__ = ["ScenarioRun", "load_run"]


def load_run(station: Any, body: dict[str, Any]) -> ScenarioRun:
    """A checked :class:`ScenarioRun` from a request body ``{"yaml": text}`` or ``{"scenario": mapping}``."""
    if ("yaml" in body) == ("scenario" in body):
        raise StationError("request body: give exactly one of 'yaml' (text) or 'scenario' (object)", field="body")
    data = body["yaml"] if "yaml" in body else body["scenario"]
    if "yaml" in body and not isinstance(data, str):
        raise StationError("field 'yaml' must be text", field="yaml")
    try:
        sc = parse_training(data)
    except ScenarioError as exc:
        raise StationError(str(exc), field="scenario") from None
    actions = [(f"events[{i}]", e.action) for i, e in enumerate(sc.events)]
    actions += [(f"triggers[{i}].do", t.action) for i, t in enumerate(sc.triggers)]
    for key, action in actions:
        if "malfunction" in action:
            try:
                parse_malfunction(action["malfunction"], unit_index=station.device.unit_index,
                                  scaling=station.device.scaling)
            except MalfunctionError as exc:
                raise StationError(f"scenario: {key}.malfunction: {exc}", field="scenario") from None
    for unit in list(sc.limits) + [t.unit for t in sc.triggers]:
        if unit not in station.device.unit_index:
            raise StationError(f"scenario: unit {unit} is not on this device", field="scenario")
    return ScenarioRun(sc)


class ScenarioRun:
    """The state of one scenario on the station (see the module docstring)."""

    def __init__(self, scenario: TrainingScenario) -> None:
        self.scenario = scenario
        self.running = False
        self.t0 = 0.0
        self.next_event = 0
        self.fired: list[str] = []
        self.released: list[str] = []
        self._outside_since: dict[str, float] = {}

    @property
    def scoring(self) -> dict[str, float]:
        return self.scenario.scoring

    @property
    def expert(self) -> dict[str, Any] | None:
        return self.scenario.expert

    def describe(self) -> dict[str, Any]:
        sc = self.scenario
        return {"name": sc.name, "notes": sc.notes, "running": self.running, "start": self.t0,
                "events": len(sc.events), "fired": [f"event {i}" for i in range(self.next_event)],
                "triggers": [t.id for t in sc.triggers], "triggers_fired": list(self.fired),
                "hints": [{"id": k, "text": v, "released": k in self.released} for k, v in sc.hints.items()]}

    def start(self, station: Any) -> None:
        station.reset_session()
        self.t0 = float(station.bank.sample_time)
        self.running, self.next_event = True, 0
        self.fired, self.released, self._outside_since = [], [], {}
        for unit, (lo, hi) in self.scenario.limits.items():
            i = station.device.unit_index[unit]
            station.lim_lo[i], station.lim_hi[i] = lo, hi
        station.notes.append({"time": self.t0, "text": f"scenario {self.scenario.name} started"})

    def stop(self, station: Any) -> None:
        self.running = False
        station.notes.append({"time": float(station.bank.sample_time),
                              "text": f"scenario {self.scenario.name} stopped"})

    def release_hint(self, station: Any, hint_id: str) -> dict[str, Any]:
        if hint_id not in self.scenario.hints:
            raise StationError(f"no hint with id {hint_id!r}", field="id", status=404)
        if hint_id not in self.released:
            self.released.append(hint_id)
            station.evaluation.hints_released.append(self.scenario.hints[hint_id])
        return {"id": hint_id, "released": True}

    def _do(self, station: Any, action: dict[str, Any], t: float, why: str) -> None:
        if "malfunction" in action:
            station.malfunction(action["malfunction"])
            text = f"{why}: malfunction {action['malfunction'].get('kind')} on unit {action['malfunction'].get('unit')}"
        elif "hint" in action:
            self.release_hint(station, action["hint"])
            text = f"{why}: hint {action['hint']} released"
        else:
            text = f"{why}: {action['say']}"
        station.notes.append({"time": t, "text": text})

    def on_tick(self, station: Any, t: float) -> None:
        if not self.running:
            return
        sc, rel = self.scenario, t - self.t0
        half = 0.5 * station.bank.dt
        while self.next_event < len(sc.events) and sc.events[self.next_event].at <= rel + half:
            event = sc.events[self.next_event]
            self.next_event += 1
            self._do(station, event.action, t, event.say or f"event at {event.at:g} s")
        for trig in sc.triggers:
            if trig.id not in self.fired and self._holds(station, trig, t):
                self.fired.append(trig.id)
                self._do(station, trig.action, t, f"trigger {trig.id}")

    def _holds(self, station: Any, trig: Any, t: float) -> bool:
        i = station.device.unit_index[trig.unit]
        ev = station.evaluation
        if trig.condition is Condition.PV_OUTSIDE:
            pv = float(station.bank.pv[i])
            if trig.band[0] <= pv <= trig.band[1]:
                self._outside_since.pop(trig.id, None)
                return False
            since = self._outside_since.setdefault(trig.id, t)
            return t - since >= trig.duration - 1e-9
        if trig.condition in (Condition.MANUAL, Condition.ACKNOWLEDGED):
            want = "manual" if trig.condition is Condition.MANUAL else "ack"
            return any(a.who == "trainee" and a.accepted and a.unit == trig.unit and a.action == want
                       for a in ev.actions)
        if trig.condition is Condition.SINCE_MALFUNCTION:
            times = [a.sim_time for a in ev.actions if a.action == "malfunction" and a.unit == trig.unit]
            return bool(times) and t - times[0] >= trig.duration - 1e-9
        return False


