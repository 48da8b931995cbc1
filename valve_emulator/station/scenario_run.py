"""A scenario (:mod:`valve_emulator.scenario`) played by the station, tick by tick.

Loaded with ``POST /api/scenario {"yaml": text}`` (or ``{"scenario": mapping}``) and checked whole against the
station's device by the one scenario parser (:func:`~valve_emulator.scenario.parse_scenario`): a bad scenario
is refused naming the key. ``start`` resets the evaluation (a new session), applies the scenario's limits, and
from then on the station calls :meth:`ScenarioRun.on_tick` after every tick: the scenario engine
(:class:`~valve_emulator.scenario.DevicePlayer`) applies the events due, and each trigger is tested on its
condition:

- ``pv_outside``: PV outside ``band`` for ``for`` simulated seconds without interruption;
- ``manual``: the trainee's action log has an accepted switch of the unit to manual since the start;
- ``acknowledged``: the trainee acknowledged an alarm of the unit since the start;
- ``since_malfunction``: ``after`` simulated seconds have passed since a malfunction on the unit.

A trigger fires once. Events and triggers do the same actions: a malfunction (logged as the instructor's, so
the evaluation times the trainee's response), a set point or register write, a line for the instructor
(``say``) or a hint released to the trainee (which costs points in the score).
"""

from __future__ import annotations

from typing import Any

from valve_emulator.device.malfunctions import Kind, Malfunction
from valve_emulator.scenario import (
    Condition,
    DevicePlayer,
    DeviceShape,
    Event,
    Hint,
    Say,
    Scenario,
    ScenarioError,
    parse_scenario,
)
from valve_emulator.scenario.player import apply_on_device
from valve_emulator.scenario.timeline import describe
from valve_emulator.station.core import StationError

__all__ = ["ScenarioRun", "load_run"]


def load_run(station: Any, body: dict[str, Any]) -> ScenarioRun:
    """A checked :class:`ScenarioRun` from a request body ``{"yaml": text}`` or ``{"scenario": mapping}``."""
    if ("yaml" in body) == ("scenario" in body):
        raise StationError("request body: give exactly one of 'yaml' (text) or 'scenario' (object)", field="body")
    data = body["yaml"] if "yaml" in body else body["scenario"]
    if "yaml" in body and not isinstance(data, str):
        raise StationError("field 'yaml' must be text", field="yaml")
    device = station.device
    try:
        sc = parse_scenario(data, source="scenario", device=DeviceShape(device.unit_index, device.scaling))
    except ScenarioError as exc:
        raise StationError(str(exc), field="scenario") from None
    actions = [e.action for e in sc.events] + [t.action for t in sc.triggers]
    comm = any(isinstance(a, Malfunction) and a.kind is Kind.COMM for a in actions)
    if comm and getattr(device.malfunctions, "comm", None) is None:
        raise StationError("scenario: a comm malfunction needs the device served over Modbus", field="scenario")
    return ScenarioRun(sc)


class ScenarioRun:
    """The state of one scenario on the station (see the module docstring)."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.running = False
        self.t0 = 0.0
        self.player: DevicePlayer | None = None
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
        sc, played = self.scenario, self.player.timeline.played if self.player is not None else 0
        return {"name": sc.name, "notes": sc.notes, "running": self.running, "start": self.t0,
                "events": len(sc.events), "fired": [f"event {i}" for i in range(played)],
                "triggers": [t.id for t in sc.triggers], "triggers_fired": list(self.fired),
                "hints": [{"id": k, "text": v, "released": k in self.released} for k, v in sc.hints.items()]}

    def start(self, station: Any) -> None:
        """A new session: the scenario's limits, then its events from now on (those at 0 s at once)."""
        station.reset_session()
        self.t0 = float(station.bank.sample_time)
        self.running = True
        self.fired, self.released, self._outside_since = [], [], {}
        for unit, (lo, hi) in self.scenario.limits.items():
            i = station.device.unit_index[unit]
            station.lim_lo[i], station.lim_hi[i] = lo, hi
        station.notes.append({"time": self.t0, "text": f"scenario {self.scenario.name} started"})

        def apply(event: Event) -> None:
            self._do(station, event.action, float(station.bank.sample_time), event.say or f"event at {event.at:g} s")

        self.player = DevicePlayer(self.scenario.events, station.bank.dt, start_tick=station.device.ticks, apply=apply)
        self.player.on_tick(station.device.ticks)

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

    def _do(self, station: Any, action: Any, t: float, why: str) -> None:
        """Carry out an event's or a trigger's action and note it for the instructor."""
        if isinstance(action, Malfunction):
            station.inject(action)
        elif isinstance(action, Hint):
            self.release_hint(station, action.id)
        elif not isinstance(action, Say):
            apply_on_device(station.device, Event(0.0, action))
        text = action.text if isinstance(action, Say) else (
            f"hint {action.id} released" if isinstance(action, Hint) else f"{describe(action)} on unit {action.unit}")
        station.notes.append({"time": t, "text": f"{why}: {text}"})

    def on_tick(self, station: Any, t: float) -> None:
        if not self.running:
            return
        self.player.on_tick(station.device.ticks)
        for trig in self.scenario.triggers:
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


