"""Scenario files: one grammar for the timelines the player runs and the lessons the station runs.

A scenario is YAML (or the same mapping as JSON)::

    name: stiction_develops            # optional, default: the file name
    description: |                     # what the trainee should see and conclude
      ...
    notes: |                           # for the instructor only (optional)
      ...
    device: ../table1/x.yaml           # the loop(s): a config file (relative to this file) or an inline mapping
                                       #   in the config format (docs/config.md); the player needs it, the
                                       #   station plays on its own device and refuses it
    unit: 1                            # the loop events act on unless they say; optional with one loop
    time_scale: 10                     # player only, default 1: simulated s per wall s
    duration: 1800                     # player only: simulated s from the start, >= the last event
    events:                            # in time order; events at the same time apply in file order
      - {at: 300, malfunction: {kind: stiction, S: 2.0, J: 0.5, ramp: 60}, say: "the packing binds"}
      - {at: 900, sp: 1.0}             # the set point of the loop's internal controller (PV units)
      - {at: 950, write: {register: kc, value: 0.25}}   # any writable register (raw = value x scale)
      - {at: 990, say: "a line for the instructor"}
    # the station adds (docs/scenarios.md): triggers, hints, limits, scoring, expert

An event is ``at`` (simulated seconds from the start, applied at the nearest tick), one action and optionally
``say``. A ``malfunction`` is a fault of the one list of kinds, :data:`valve_emulator.device.malfunctions.KINDS`
(its ``unit`` defaults to the scenario's), checked by
:func:`~valve_emulator.device.malfunctions.parse_malfunction`, the check the station's HTTP API and the testing
kit's ``inject`` use.

The older event form, ``{at: 300, event: stiction, S: 2.0, J: 0.5}``, is read as the same malfunction:
``event: KIND`` with the parameters beside it, for every kind; ``event: normal`` is ``clear``; ``event: sp,
value: x`` is ``sp: x``; ``event: write, register: r, value: x`` is ``write: {register: r, value: x}``;
``event: noise, std: x`` gives ``std`` in % of ``pv_range`` (as the ``noise`` register), converted to PV units;
``event: comm`` sets both ``fault`` and ``delay_ms`` (default 0), and its ``duration`` adds the event that sets
them back to 0. Errors in an old-form event name its own keys (``events[3].Q``).

Everything is checked when the scenario is loaded -- before an emulator starts or a register is written -- and
a problem raises :class:`ScenarioError` (a :class:`~valve_emulator.errors.UserError`) naming the file, line and
key: unknown keys, kinds, units or hints, wrong values, times that go backwards or beyond ``duration``, and
changes the device would refuse, checked with the device's own register map.

Pure: reads the files it is given, no sockets, no clock. The engine that plays it is
:mod:`valve_emulator.scenario.player`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Final

from valve_emulator.config import ConfigError, LoopConfig, ServerConfig, load_server, server_from_mapping
from valve_emulator.device.malfunctions import Kind, Malfunction, MalfunctionError, parse_malfunction
from valve_emulator.device.registers import REGISTERS, UNIT_REGISTERS, Register, RegisterError, Scaling, decode_write
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.scenario._yaml import ScenarioError, Where, load_yaml

__all__ = ["EVENT_KINDS", "Condition", "DeviceShape", "Event", "Hint", "RegisterWrite", "Say", "Scenario",
           "ScenarioError", "SetPoint", "Trigger", "load_scenario", "parse_scenario"]

_TOP: Final = ("name", "description", "notes", "device", "unit", "time_scale", "duration", "events", "triggers",
               "hints", "limits", "scoring", "expert")
_PLAYER_ONLY: Final = ("device", "time_scale", "duration")
_SCORING: Final = ("iae", "outside", "response", "hint")
_BY_NAME: Final = {r.name: r for r in REGISTERS + UNIT_REGISTERS}
_UNIT_NAMES: Final = frozenset(r.name for r in UNIT_REGISTERS)
#: the older ``event:`` names that are not fault kinds, and what they became
_OLD_NAMES: Final = {"normal": "malfunction: {kind: clear}", "sp": "sp: value",
                     "write": "write: {register, value}"}
#: every name ``event:`` takes: the fault kinds, then the older names
EVENT_KINDS: Final = tuple(k.value for k in Kind) + tuple(_OLD_NAMES)


# --- the checked scenario -----------------------------------------------------------------------------

@dataclass(frozen=True)
class SetPoint:
    """The set point of loop ``index``'s internal controller: ``value`` PV units, ``word`` its register word."""

    unit: int
    index: int
    value: float
    word: int


@dataclass(frozen=True)
class RegisterWrite:
    """A write of register ``register`` of loop ``index``: ``value`` in the register map's units."""

    unit: int
    index: int
    register: str
    value: float
    word: int


@dataclass(frozen=True)
class Say:
    """A line for the instructor."""

    text: str


@dataclass(frozen=True)
class Hint:
    """A hint released to the trainee (the station)."""

    id: str


Action = Malfunction | SetPoint | RegisterWrite | Say | Hint


def kind_of(action: Action) -> str:
    """``stiction``, ``clear``, ... for a malfunction; ``sp``, ``write``, ``say``, ``hint`` otherwise."""
    if isinstance(action, Malfunction):
        return action.kind.value
    return {SetPoint: "sp", RegisterWrite: "write", Say: "say", Hint: "hint"}[type(action)]


def describe(action: Action) -> str:
    """``stiction S=5 J=2``, ``load flow=3 ramp=60``, ``sp value=1``, ``write register=kc value=0.25`` ..."""
    if isinstance(action, Malfunction):
        params = {**action.params, **({"ramp": action.ramp} if action.ramp else {})}
        return " ".join([action.kind.value] + [f"{k}={v:g}" for k, v in params.items()])
    if isinstance(action, SetPoint):
        return f"sp value={action.value:g}"
    if isinstance(action, RegisterWrite):
        return f"write register={action.register} value={action.value:g}"
    return f"say {action.text}" if isinstance(action, Say) else f"hint {action.id}"


@dataclass(frozen=True)
class Event:
    """One timed action: when (simulated s from the start), what, a line for the instructor, its file line."""

    at: float
    action: Action
    say: str = ""
    line: int = 0

    @property
    def kind(self) -> str:
        return kind_of(self.action)

    def describe(self) -> str:
        return describe(self.action)


class Condition(StrEnum):
    PV_OUTSIDE = "pv_outside"
    MANUAL = "manual"
    ACKNOWLEDGED = "acknowledged"
    SINCE_MALFUNCTION = "since_malfunction"


@dataclass(frozen=True, kw_only=True)
class Trigger:
    """A station trigger: fires ``action`` once, when ``condition`` on ``unit`` first holds."""

    id: str
    condition: Condition
    unit: int
    band: tuple[float, float] = (-math.inf, math.inf)
    duration: float = 0.0        # pv_outside: for; since_malfunction: after
    action: Action


@dataclass(frozen=True)
class DeviceShape:
    """What the parser checks a scenario against: the device's units (unit -> loop index) and scalings."""

    unit_index: Mapping[int, int]
    scaling: Scaling

    @classmethod
    def of_config(cls, config: ServerConfig) -> DeviceShape:
        index: dict[int, int] = {}
        for i, lp in enumerate(config.loops):
            index.setdefault(lp.device.unit, i)
        return cls(index, Scaling.from_config(config))

    @property
    def units(self) -> list[int]:
        return list(self.unit_index)


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """A checked scenario (see the module docstring); ``config``, ``duration`` are ``None`` for the station's."""

    name: str
    description: str = ""
    notes: str = ""
    source: str
    config: ServerConfig | None = None
    unit: int | None = None
    duration: float | None = None
    time_scale: float = 1.0
    events: tuple[Event, ...] = ()
    triggers: tuple[Trigger, ...] = ()
    hints: dict[str, str] = field(default_factory=dict)
    limits: dict[int, tuple[float, float]] = field(default_factory=dict)
    scoring: dict[str, float] = field(default_factory=dict)
    expert: dict[str, Any] | None = None

    @property
    def index(self) -> int:
        """Position of the scenario's loop in ``config.loops`` (and in the device)."""
        return next(i for i, lp in enumerate(self.config.loops) if lp.device.unit == self.unit)

    @property
    def loop(self) -> LoopConfig:
        return self.config.loops[self.index]

    @property
    def dt(self) -> float:
        """Simulated seconds per device tick."""
        return self.config.device.tick

    def tick_of(self, t: float) -> int:
        """The tick (counted from the start of the scenario) at which time ``t`` happens: the nearest one."""
        return round(t / self.dt)


# --- values -------------------------------------------------------------------------------------------

def _number(value: Any, key: str, where: Where, *, lo: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise where.fail(key, f"must be a finite number, got {value!r}")
    if lo is not None and value < lo:
        raise where.fail(key, f"must be >= {lo:g}, got {value!r}")
    return float(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _mapping(value: Any, key: str, where: Where) -> Mapping:
    if not isinstance(value, Mapping):
        raise where.fail(key, f"must be a mapping, got {type(value).__name__}")
    return value


def _text(value: Any, key: str, where: Where) -> str:
    if not isinstance(value, str):
        raise where.fail(key, f"must be text, got {value!r}")
    return value


def _unit(value: Any, key: str, where: Where, shape: DeviceShape) -> int:
    if isinstance(value, bool) or value not in shape.unit_index:
        raise where.fail(key, f"the device has no loop on unit {value!r} (units: {shape.units})")
    return value


def _raw(reg: Register, value: float, key: str, where: Where) -> int:
    """Register word for a physical ``value`` (raw = value x scale); int16 as two's complement."""
    raw = round(value * reg.scale)
    if reg.type == "int16":
        if not -0x8000 <= raw <= 0x7FFF:
            raise where.fail(key, f"register {reg.name}: {raw} out of range {reg.lo}..{reg.hi}")
        return raw & 0xFFFF
    return raw


def _device_accepts(name: str, word: int, index: int, key: str, where: Where, shape: DeviceShape) -> None:
    """The device's own rule for a write: the check a Modbus write with instructor rights gets."""
    reg = _BY_NAME[name]
    if name in _UNIT_NAMES:
        if not reg.lo <= word <= reg.hi:
            raise where.fail(key, f"register {name}: {word} out of range {reg.lo}..{reg.hi}")
        return
    try:
        decode_write(reg.address, [word], shape.scaling, index, auto=False, role=INSTRUCTOR)
    except RegisterError as exc:
        raise where.fail(key, str(exc)) from None


# --- actions ------------------------------------------------------------------------------------------

class _Context:
    """What an action is checked against: the device, the scenario's unit and hints, and where keys are."""

    def __init__(self, where: Where, shape: DeviceShape, unit: int | None, hints: Mapping[str, str]) -> None:
        self.where, self.shape, self.unit, self.hints = where, shape, unit, hints

    def default_unit(self, key: str) -> int:
        if self.unit is None:
            raise self.where.fail(key, f"which loop? the device has units {self.shape.units}; give unit: N here "
                                       "or at the top of the scenario")
        return self.unit


def _malfunction(body: Mapping, prefix: str, ctx: _Context) -> Malfunction:
    """``body`` checked by the device's malfunction check; errors name ``prefix.field``."""
    request = {"unit": ctx.default_unit(prefix), **body} if "unit" not in body else dict(body)
    try:
        return parse_malfunction(request, unit_index=ctx.shape.unit_index, scaling=ctx.shape.scaling)
    except MalfunctionError as exc:
        key = prefix if exc.field == "body" else f"{prefix}.{exc.field}"
        raise ctx.where.fail(key, str(exc)) from None


def _set_point(value: Any, key: str, ctx: _Context) -> SetPoint:
    unit = ctx.default_unit(key)
    index = ctx.shape.unit_index[unit]
    x = _number(value, key, ctx.where)
    lo, hi = float(ctx.shape.scaling.pv_lo[index]), float(ctx.shape.scaling.pv_hi[index])
    word = _raw(_BY_NAME["sp"], 100.0 * (x - lo) / (hi - lo), key, ctx.where)
    _device_accepts("sp", word, index, key, ctx.where, ctx.shape)
    return SetPoint(unit, index, x, word)


def _register_write(value: Any, key: str, ctx: _Context) -> RegisterWrite:
    m = _mapping(value, key, ctx.where)
    for k in m:
        if k not in ("register", "value", "unit"):
            raise ctx.where.fail(f"{key}.{k}", "unknown key (a write has register, value and optionally unit)")
    for k in ("register", "value"):
        if k not in m:
            raise ctx.where.fail(key, f"a write needs {k!r}")
    unit = _unit(m["unit"], f"{key}.unit", ctx.where, ctx.shape) if "unit" in m else ctx.default_unit(key)
    name = m["register"]
    if not isinstance(name, str) or name not in _BY_NAME:
        raise ctx.where.fail(f"{key}.register", f"the device has no register {name!r} "
                                                f"(registers: {', '.join(_BY_NAME)})")
    x = _number(m["value"], f"{key}.value", ctx.where)
    index = ctx.shape.unit_index[unit]
    word = _raw(_BY_NAME[name], x, f"{key}.value", ctx.where)
    _device_accepts(name, word, index, key, ctx.where, ctx.shape)
    return RegisterWrite(unit, index, name, x, word)


#: the actions of an event or a trigger (what each takes: the module docstring)
_ACTIONS: Final = ("malfunction", "sp", "write", "say", "hint")


def _action(name: str, arg: Any, key: str, ctx: _Context) -> Action:
    """Action ``name`` (one of :data:`_ACTIONS`) with its argument; ``key`` is where the argument is."""
    if name == "malfunction":
        return _malfunction(_mapping(arg, key, ctx.where), key, ctx)
    if name == "sp":
        return _set_point(arg, key, ctx)
    if name == "write":
        return _register_write(arg, key, ctx)
    if name == "hint":
        if arg not in ctx.hints:
            raise ctx.where.fail(key, f"no hint with id {arg!r} (hints: {', '.join(ctx.hints) or 'none'})")
        return Hint(arg)
    return Say(_text(arg, key, ctx.where))


def _one_action(m: Mapping, key: str, ctx: _Context) -> Action:
    """The one action of a mapping such as ``{malfunction: {...}}`` or ``{hint: id}``."""
    names = [k for k in m if k in _ACTIONS]
    if len(names) != 1:
        raise ctx.where.fail(key, f"needs exactly one of {', '.join(_ACTIONS)}, got {', '.join(map(str, m)) or 'none'}")
    return _action(names[0], m[names[0]], f"{key}.{names[0]}", ctx)


# --- events -------------------------------------------------------------------------------------------

def _old_event(m: Mapping, key: str, ctx: _Context) -> tuple[Action, float | None]:
    """An event of the older form ``{event: KIND, ...parameters}`` as its action (see the module docstring),
    and the ``duration`` of a ``comm`` event. Errors name the old keys."""
    where = ctx.where
    kind = m["event"]
    if not isinstance(kind, str) or kind not in EVENT_KINDS:
        raise where.fail(f"{key}.event", f"unknown event type {kind!r} (known: {', '.join(EVENT_KINDS)})")
    params = {k: v for k, v in m.items() if k not in ("at", "event", "say")}
    allowed = {"sp": ("value",), "write": ("register", "value"), "normal": ()}.get(kind)
    if allowed is not None:
        for k in params:
            if k not in allowed:
                raise where.fail(f"{key}.{k}", f"unknown key for a {kind} event (allowed: at, event, say"
                                               f"{''.join(', ' + a for a in allowed)})")
        for k in allowed:
            if k not in params:
                raise where.fail(key, f"a {kind} event needs {k!r}")
        if kind == "sp":
            return _set_point(params["value"], f"{key}.value", ctx), None
        if kind == "write":
            return _register_write(params, key, ctx), None
        return _malfunction({"kind": Kind.CLEAR.value}, key, ctx), None
    duration = None
    if kind == Kind.COMM:
        if "fault" not in params:
            raise where.fail(key, "a comm event needs 'fault'")
        params.setdefault("delay_ms", 0)
        if "duration" in params:
            duration = _number(params.pop("duration"), f"{key}.duration", where)
            if duration <= 0:
                raise where.fail(f"{key}.duration", "must be > 0 s")
    unit = params.get("unit", ctx.unit)
    if kind == Kind.NOISE and unit in ctx.shape.unit_index and _is_number(params.get("std")):
        index = ctx.shape.unit_index[unit]   # the old std is in % of pv_range (the register's unit)
        params["std"] = params["std"] * float(ctx.shape.scaling.pv_hi[index] - ctx.shape.scaling.pv_lo[index]) / 100
    return _malfunction({"kind": kind, **params}, key, ctx), duration


def _events(m: Any, key: str, ctx: _Context) -> list[Event]:
    """The event at ``key`` (and, for an old-form ``comm`` with a ``duration``, the one that ends it)."""
    where = ctx.where
    if not isinstance(m, Mapping):
        raise where.fail(key, "must be a mapping such as {at: 60, malfunction: {kind: seize}}")
    if "at" not in m:
        raise where.fail(key, "missing key 'at'")
    at = _number(m["at"], f"{key}.at", where, lo=0.0)
    say = _text(m.get("say", ""), f"{key}.say", where)
    line = where.line(key)
    if "event" in m:
        action, duration = _old_event(m, key, ctx)
        events = [Event(at, action, say, line)]
        if duration is not None:
            end = _malfunction({"unit": action.unit, "kind": "comm", "fault": 0, "delay_ms": 0}, key, ctx)
            events.append(Event(at + duration, end, f"end of the communication fault of line {line}", line))
        return events
    for k in m:
        if k not in ("at", "say", *_ACTIONS):
            raise where.fail(f"{key}.{k}", f"unknown key (an event has at, one of {', '.join(_ACTIONS)}, and say)")
    if not any(k in m for k in _ACTIONS if k != "say"):
        if not say:
            raise where.fail(key, f"needs one of {', '.join(_ACTIONS)}")
        return [Event(at, Say(say), "", line)]
    return [Event(at, _one_action({k: v for k, v in m.items() if k not in ("at", "say")}, key, ctx), say, line)]


def _timeline(raw: Any, ctx: _Context, duration: float | None) -> tuple[Event, ...]:
    where = ctx.where
    if not isinstance(raw, list):
        raise where.fail("events", "must be a list of events")
    events: list[Event] = []
    ends: list[Event] = []
    for i, m in enumerate(raw):
        key = f"events[{i}]"
        event, *end = _events(m, key, ctx)
        if events and event.at < events[-1].at:
            raise where.fail(f"{key}.at", f"time goes backwards: {event.at:g} s after {events[-1].at:g} s "
                                          f"(line {events[-1].line}); list events in time order")
        if duration is not None and event.at > duration:
            raise where.fail(f"{key}.at", f"{event.at:g} s is after the end of the scenario (duration {duration:g} s)")
        events.append(event)
        ends += end
    for ev in ends:
        if duration is not None and ev.at > duration:
            raise ScenarioError(f"{where.source}:{ev.line}: the communication fault ends at {ev.at:g} s, after the "
                                f"end of the scenario (duration {duration:g} s)")
    return tuple(sorted(events + ends, key=lambda ev: ev.at))   # stable: file order among events at one time


# --- the station's additions: triggers, hints, limits, scoring ----------------------------------------

_TRIGGER_ARGS: Final = {Condition.PV_OUTSIDE: ("unit", "band", "for"), Condition.SINCE_MALFUNCTION: ("unit", "after"),
                        Condition.MANUAL: ("unit",), Condition.ACKNOWLEDGED: ("unit",)}


def _band(value: Any, key: str, where: Where) -> tuple[float, float]:
    if not (isinstance(value, list) and len(value) == 2):
        raise where.fail(key, f"must be [low, high], got {value!r}")
    lo, hi = _number(value[0], f"{key}[0]", where), _number(value[1], f"{key}[1]", where)
    if lo >= hi:
        raise where.fail(key, f"low must be below high, got {value!r}")
    return lo, hi


def _trigger(value: Any, key: str, ctx: _Context) -> Trigger:
    where = ctx.where
    m = _mapping(value, key, where)
    for k in m:
        if k not in ("id", "when", "do"):
            raise where.fail(f"{key}.{k}", "unknown key (a trigger has id, when, do)")
    tid = m.get("id")
    if not isinstance(tid, str) or not tid:
        raise where.fail(f"{key}.id", f"must be a non-empty text, got {tid!r}")
    when = _mapping(m.get("when"), f"{key}.when", where)
    if len(when) != 1:
        raise where.fail(f"{key}.when", f"must hold one condition of {', '.join(c.value for c in Condition)}")
    (name, args), = when.items()
    try:
        cond = Condition(name)
    except ValueError:
        raise where.fail(f"{key}.when.{name}", f"unknown condition; one of {', '.join(c.value for c in Condition)}") \
            from None
    at = f"{key}.when.{name}"
    args = _mapping(args, at, where)
    for k in args:
        if k not in _TRIGGER_ARGS[cond]:
            raise where.fail(f"{at}.{k}", f"unknown key (takes {', '.join(_TRIGGER_ARGS[cond])})")
    unit = _unit(args["unit"], f"{at}.unit", where, ctx.shape) if "unit" in args else ctx.default_unit(at)
    band, duration = (-math.inf, math.inf), 0.0
    if cond is Condition.PV_OUTSIDE:
        band = _band(args.get("band"), f"{at}.band", where)
        duration = _number(args.get("for", 0.0), f"{at}.for", where, lo=0.0)
    elif cond is Condition.SINCE_MALFUNCTION:
        duration = _number(args.get("after"), f"{at}.after", where, lo=0.0)
    action = _one_action(_mapping(m.get("do"), f"{key}.do", where), f"{key}.do", ctx)
    return Trigger(id=tid, condition=cond, unit=unit, band=band, duration=duration, action=action)


def _hints(raw: Any, where: Where) -> dict[str, str]:
    hints: dict[str, str] = {}
    for i, h in enumerate(raw or []):
        h = _mapping(h, f"hints[{i}]", where)
        if not isinstance(h.get("id"), str) or not isinstance(h.get("text"), str):
            raise where.fail(f"hints[{i}]", "needs id and text")
        hints[h["id"]] = h["text"]
    return hints


def _limits(raw: Any, where: Where, shape: DeviceShape) -> dict[int, tuple[float, float]]:
    return {_unit(u, f"limits.{u}", where, shape): _band(lim, f"limits.{u}", where)
            for u, lim in _mapping(raw or {}, "limits", where).items()}


def _scoring(raw: Any, where: Where) -> dict[str, float]:
    scoring = {}
    for k, v in _mapping(raw or {}, "scoring", where).items():
        if k not in _SCORING:
            raise where.fail(f"scoring.{k}", f"unknown weight (one of {', '.join(_SCORING)})")
        scoring[k] = _number(v, f"scoring.{k}", where, lo=0.0)
    return scoring


# --- the file -----------------------------------------------------------------------------------------

def _device(value: Any, where: Where, base: Path) -> ServerConfig:
    line = where.line("device")
    try:
        if isinstance(value, str):
            path = Path(value)
            return load_server(path if path.is_absolute() else base / path)
        if isinstance(value, Mapping):
            return server_from_mapping(value, source=f"{where.source}:{line}: device")
    except ConfigError as exc:
        raise ScenarioError(f"{where.source}:{line}: device: {exc}") from None
    raise where.fail("device", "must be a config file name or a mapping in the config format")


def _player_keys(data: Mapping, where: Where, base: Path) -> tuple[ServerConfig, float, float]:
    """The device, duration and time-scale of a scenario the player runs (all in the file)."""
    for k in ("device", "duration", "events"):
        if k not in data:
            raise ScenarioError(f"{where.source}:1: missing key {k!r}")
    config = _device(data["device"], where, base)
    duration = _number(data["duration"], "duration", where, lo=0.0)
    if duration <= 0:
        raise where.fail("duration", "must be > 0 s")
    time_scale = _number(data.get("time_scale", 1.0), "time_scale", where, lo=0.0)
    if time_scale <= 0:
        raise where.fail("time_scale", "must be > 0")
    return config, duration, time_scale


def parse_scenario(data: str | Mapping, *, source: str = "<scenario>", base: Path | None = None,
                   device: DeviceShape | None = None) -> Scenario:
    """Parse and check a scenario given as YAML text (or as the mapping it holds).

    Without ``device`` the scenario is the player's: it names its device (a config file relative to ``base``,
    or inline) and its duration. With ``device`` (the station's) it is checked against that device and may
    not name one.
    """
    if isinstance(data, str):
        data, where = load_yaml(data, source)
    else:
        where = Where(source)
    if not isinstance(data, Mapping):
        raise ScenarioError(f"{where.at('')}: a scenario is a mapping of events (and name, device, duration ...)")
    for k in data:
        if k not in _TOP:
            raise where.fail(str(k), f"unknown key (allowed: {', '.join(_TOP)})")
    config, duration, time_scale = None, None, 1.0
    if device is None:
        config, duration, time_scale = _player_keys(data, where, base if base is not None else Path("."))
        device = DeviceShape.of_config(config)
    else:
        for k in _PLAYER_ONLY:
            if k in data:
                raise where.fail(k, "the station plays a scenario on its own device, at its own speed, until "
                                    "stopped; remove the key")
    unit = _scenario_unit(data, where, device, player=config is not None)
    hints = _hints(data.get("hints"), where)
    ctx = _Context(where, device, unit, hints)
    events = _timeline(data.get("events", []), ctx, duration)
    triggers = tuple(_trigger(t, f"triggers[{i}]", ctx) for i, t in enumerate(data.get("triggers") or []))
    ids = [t.id for t in triggers]
    if len(set(ids)) != len(ids):
        raise where.fail("triggers", f"trigger ids must be unique, got {ids}")
    texts = {k: _text(data.get(k, default), k, where)
             for k, default in (("name", Path(source).stem), ("description", ""), ("notes", ""))}
    expert = data.get("expert")
    if expert is not None:
        _mapping(expert, "expert", where)
    return Scenario(name=texts["name"], description=texts["description"].strip(), notes=texts["notes"].strip(),
                    source=source, config=config, unit=unit, duration=duration, time_scale=time_scale,
                    events=events, triggers=triggers, hints=hints, limits=_limits(data.get("limits"), where, device),
                    scoring=_scoring(data.get("scoring"), where), expert=expert)


def _scenario_unit(data: Mapping, where: Where, shape: DeviceShape, *, player: bool) -> int | None:
    """The scenario's loop: ``unit``, or the device's only one; the player needs one, the station not."""
    if "unit" in data:
        return _unit(data["unit"], "unit", where, shape)
    if len(shape.units) == 1:
        return shape.units[0]
    if player:
        raise ScenarioError(f"{where.source}:1: the device has several loops (units {shape.units}); "
                            "say which: unit: N")
    return None


def load_scenario(path: str | Path) -> Scenario:
    """Read and check a player's scenario file (see the module docstring); :class:`ScenarioError` names the line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}:1: cannot read the scenario: {exc}") from None
    return parse_scenario(text, source=str(path), base=path.parent)
