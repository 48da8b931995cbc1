"""Operator-training scenarios: a timeline of instructor events, parsed and checked before anything runs.

A scenario is a YAML file::

    name: stiction_develops            # optional, default: the file name
    description: |                     # what the trainee should see and conclude
      ...
    device: ../table1/x.yaml           # the loop(s): a config file (relative to this file) or an inline
                                       #   mapping in the config format (docs/config.md)
    unit: 1                            # which loop; optional when the device has one loop
    time_scale: 10                     # optional, default 1: simulated s per wall s when the emulator is started
    duration: 1800                     # simulated s from the start, >= the last event
    events:                            # in time order; events at the same time apply in file order
      - {at: 300, event: stiction, S: 2.0, J: 0.5, say: "the packing starts to bind"}

Every event has ``at`` (simulated seconds from the start of the scenario, applied at the nearest tick),
``event`` (its type) and optionally ``say`` (a line shown to the instructor when it happens). The types
and their keys, and the registers they write (:mod:`valve_emulator.device.registers`):

==========  ==================================  =====================================================
event       keys                                writes
==========  ==================================  =====================================================
stiction    ``S``, ``J`` (% travel, >= one)     ``S``, ``J``: stiction appears, grows or is cured
load        ``flow`` (% flow, -100..100)        ``load``: a load disturbance added to the plant input
noise       ``std`` (% of pv_range, 0..100)     ``noise``: PV measurement noise (standard deviation)
seize       --                                  ``fault`` = 1: the valve sticks completely
release     --                                  ``fault`` = 0
sp          ``value`` (PV units)                ``sp``: set point of the loop's internal controller
normal      --                                  ``S``, ``J`` and ``noise`` back to the device config,
                                                ``load`` 0, ``fault`` 0 (the set point is left alone)
write       ``register`` (a name), ``value``    any writable register, ``value`` in the units of the
                                                register map (raw = value × scale)
comm        ``fault`` (0..5 or its name),       ``comm_fault``, ``comm_delay_ms`` of the unit: a
            ``delay_ms`` (0..10000),            communication fault (``none``, ``no_response``,
            ``duration`` (s, optional)          ``busy``, ``failure``, ``close``, ``bad_crc``); with
                                                ``duration`` both go back to 0 that much later. No
                                                other event may fall inside a ``no_response``,
                                                ``busy``, ``failure`` or ``close`` fault: the unit
                                                would not carry it out
==========  ==================================  =====================================================

Everything is checked when the file is loaded -- before an emulator starts or a register is written --
and a problem raises :class:`ScenarioError` (a ``ValueError``) naming the file and line: unknown keys or
event types, wrong values, times that go backwards or beyond ``duration``, and writes the device would
refuse, checked with the device's own register map (a register it does not have, a read-only one, a set
point on a loop without internal controller, a value out of range).

Pure: reads the files it is given, no sockets, no clock. Sits beside the device layer (it uses the
register map); the engine that plays it is :mod:`valve_emulator.scenario.player`, its Modbus front end
:mod:`valve_emulator.clients.scenario`.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import yaml

from valve_emulator.config import ConfigError, LoopConfig, ServerConfig, load_server, server_from_mapping
from valve_emulator.device.registers import (
    REGISTERS,
    UNIT_REGISTERS,
    CommFault,
    Register,
    RegisterError,
    Scaling,
    decode_write,
)

__all__ = ["EVENT_TYPES", "Event", "Scenario", "ScenarioError", "load_scenario", "parse_scenario"]

#: event type -> (required keys, optional keys), besides ``at``, ``event`` and ``say``
EVENT_TYPES: Final[dict[str, tuple[tuple[str, ...], tuple[str, ...]]]] = {
    "stiction": ((), ("S", "J")),
    "load": (("flow",), ()),
    "noise": (("std",), ()),
    "seize": ((), ()),
    "release": ((), ()),
    "sp": (("value",), ()),
    "normal": ((), ()),
    "write": (("register", "value"), ()),
    "comm": (("fault",), ("delay_ms", "duration")),
}
_COMMON: Final = ("at", "event", "say")
_TOP: Final = ("name", "description", "device", "unit", "time_scale", "duration", "events")
_BY_NAME: Final = {r.name: r for r in REGISTERS + UNIT_REGISTERS}
_UNIT_NAMES: Final = frozenset(r.name for r in UNIT_REGISTERS)


class ScenarioError(ValueError):
    """A scenario that cannot be played; the message starts with ``file:line:``."""


@dataclass(frozen=True)
class Event:
    """One instructor event: when, what, and the raw register words it writes (in address order)."""

    at: float
    kind: str
    params: tuple[tuple[str, Any], ...]
    writes: tuple[tuple[str, int], ...]
    say: str = ""
    line: int = 0

    def describe(self) -> str:
        """``stiction S=5 J=2``, ``seize`` ... for the instructor's log."""
        return " ".join([self.kind] + [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.params])


@dataclass(frozen=True)
class Scenario:
    """A checked scenario (see the module docstring)."""

    name: str
    description: str
    source: str
    config: ServerConfig
    unit: int
    duration: float
    time_scale: float
    events: tuple[Event, ...]

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

    def server_config(self, *, instructor_hosts: tuple[str, ...] = ("127.0.0.1",)) -> ServerConfig:
        """The device config with instructor writes allowed (from ``instructor_hosts`` unless the config
        already allows them), for an emulator the scenario starts itself."""
        dev = self.config.device
        if dev.instructor_writes:
            return self.config
        dev = dataclasses.replace(dev, instructor_writes=True, instructor_hosts=instructor_hosts)
        loops = tuple(dataclasses.replace(lp, device=dataclasses.replace(dev, unit=lp.device.unit))
                      for lp in self.config.loops)
        return dataclasses.replace(self.config, device=dev, loops=loops)


# --- YAML with line numbers ---------------------------------------------------------------------------

def _index(node: yaml.Node | None, key: str, lines: dict[str, int], source: str) -> None:
    """Record the 1-based line of every key and list item under ``key``; refuse duplicate keys."""
    if isinstance(node, yaml.MappingNode):
        seen: dict[str, int] = {}
        for k, v in node.value:
            if not isinstance(k, yaml.ScalarNode):
                continue
            child, line = (f"{key}.{k.value}" if key else k.value), k.start_mark.line + 1
            if k.value in seen:
                raise ScenarioError(f"{source}:{line}: duplicate key {child} (first on line {seen[k.value]})")
            seen[k.value] = lines[child] = line
            _index(v, child, lines, source)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            lines[f"{key}[{i}]"] = item.start_mark.line + 1
            _index(item, f"{key}[{i}]", lines, source)


def _load_yaml(text: str, source: str) -> tuple[Any, dict[str, int]]:
    loader = yaml.SafeLoader(text)
    lines: dict[str, int] = {}
    try:
        node = loader.get_single_node()
        _index(node, "", lines, source)
        data = None if node is None else loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = "; ".join(str(p) for p in (exc.context, exc.problem) if p)
        raise ScenarioError(f"{source}:{mark.line + 1 if mark else 1}: YAML syntax error: {what}") from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}:1: YAML error: {exc}") from None
    finally:
        loader.dispose()
    return data, lines


class _Where:
    """Turns a dotted key into ``file:line: key`` for messages (the nearest line known)."""

    def __init__(self, source: str, lines: dict[str, int]) -> None:
        self.source, self.lines = source, lines

    def line(self, key: str) -> int:
        while key:
            if key in self.lines:
                return self.lines[key]
            cut = max(key.rfind("."), key.rfind("["))
            key = key[:max(cut, 0)]
        return 1

    def fail(self, key: str, message: str) -> ScenarioError:
        return ScenarioError(f"{self.source}:{self.line(key)}: {key}: {message}")


def _number(value: Any, key: str, where: _Where, *, lo: float | None = None, hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise where.fail(key, f"must be a finite number, got {value!r}")
    x = float(value)
    if (lo is not None and x < lo) or (hi is not None and x > hi):
        span = f"{lo:g}..{hi:g}" if lo is not None and hi is not None else (f">= {lo:g}" if lo is not None
                                                                              else f"<= {hi:g}")
        raise where.fail(key, f"must be {span}, got {value!r}")
    return x


# --- events -> register words -------------------------------------------------------------------------

def _raw(reg: Register, value: float, key: str, where: _Where) -> int:
    """Register word for a physical ``value`` (raw = value × scale); int16 as two's complement."""
    raw = round(value * reg.scale)
    if reg.type == "int16":
        if not -0x8000 <= raw <= 0x7FFF:
            raise where.fail(key, f"register {reg.name}: {raw} out of range {reg.lo}..{reg.hi}")
        return raw & 0xFFFF
    return raw


def _writes(kind: str, p: dict[str, Any], key: str, loop: LoopConfig, where: _Where) -> list[tuple[str, int]]:
    lo, hi = loop.plant.pv_range
    def pct(x):
        return 100.0 * (x - lo) / (hi - lo)
    if kind == "stiction":
        return [(n, _raw(_BY_NAME[n], p[n], f"{key}.{n}", where)) for n in ("S", "J") if n in p]
    if kind == "load":
        return [("load", _raw(_BY_NAME["load"], p["flow"], f"{key}.flow", where))]
    if kind == "noise":
        return [("noise", _raw(_BY_NAME["noise"], p["std"], f"{key}.std", where))]
    if kind == "comm":
        return [("comm_fault", int(p["fault"])), ("comm_delay_ms", _raw(_BY_NAME["comm_delay_ms"],
                                                                        p.get("delay_ms", 0.0), key, where))]
    if kind in ("seize", "release"):
        return [("fault", int(kind == "seize"))]
    if kind == "sp":
        return [("sp", _raw(_BY_NAME["sp"], pct(p["value"]), f"{key}.value", where))]
    if kind == "normal":
        v = loop.valve
        noise = 100.0 * loop.plant.noise / (hi - lo)
        return [("S", _raw(_BY_NAME["S"], v.S, key, where)), ("J", _raw(_BY_NAME["J"], v.J, key, where)),
                ("load", 0), ("noise", _raw(_BY_NAME["noise"], min(noise, 100.0), key, where)), ("fault", 0)]
    # write
    name = p["register"]
    if not isinstance(name, str) or name not in _BY_NAME:
        raise where.fail(f"{key}.register", f"the device has no register {name!r} "
                                            f"(registers: {', '.join(_BY_NAME)})")
    return [(name, _raw(_BY_NAME[name], p["value"], f"{key}.value", where))]


def _event(m: Any, key: str, where: _Where, loop: LoopConfig, scaling: Scaling, index: int) -> Event:
    if not isinstance(m, Mapping):
        raise where.fail(key, "must be a mapping such as {at: 60, event: seize}")
    for k in ("at", "event"):
        if k not in m:
            raise where.fail(key, f"missing key {k!r}")
    kind = m["event"]
    if not isinstance(kind, str) or kind not in EVENT_TYPES:
        raise where.fail(f"{key}.event", f"unknown event type {kind!r} (known: {', '.join(EVENT_TYPES)})")
    required, optional = EVENT_TYPES[kind]
    allowed = _COMMON + required + optional
    for k in m:
        if k not in allowed:
            raise where.fail(f"{key}.{k}", f"unknown key for a {kind} event (allowed: {', '.join(allowed)})")
    for k in required:
        if k not in m:
            raise where.fail(key, f"a {kind} event needs {k!r}")
    if kind == "stiction" and not any(k in m for k in optional):
        raise where.fail(key, "a stiction event needs S, J or both")
    at = _number(m["at"], f"{key}.at", where, lo=0.0)
    say = m.get("say", "")
    if not isinstance(say, str):
        raise where.fail(f"{key}.say", f"must be text, got {say!r}")
    params: dict[str, Any] = {}
    for k in required + optional:
        if k in m:
            params[k] = m[k] if k in ("register", "fault") else _number(m[k], f"{key}.{k}", where)
    if kind == "comm":
        params["fault"] = _comm_fault(m["fault"], f"{key}.fault", where)
        if "duration" in params and params["duration"] <= 0:
            raise where.fail(f"{key}.duration", "must be > 0 s")
    writes = _writes(kind, params, key, loop, where)
    for name, raw in writes:  # the device's own rules: the same check a write over Modbus gets
        if name in _UNIT_NAMES:
            lo, hi = _BY_NAME[name].write
            if not lo <= raw <= hi:
                raise where.fail(key, f"{kind}: register {name}: {raw} out of range {lo}..{hi}")
            continue
        try:
            decode_write(_BY_NAME[name].address, [raw], scaling, index, auto=False, instructor=True)
        except RegisterError as exc:
            raise where.fail(key, f"{kind}: {exc}") from None
    writes.sort(key=lambda w: _BY_NAME[w[0]].address)
    return Event(at, kind, tuple(params.items()), tuple(writes), say, where.line(key))


def _comm_fault(value: Any, key: str, where: _Where) -> int:
    """A ``comm_fault`` value given as 0..5 or as the name of a :class:`CommFault`."""
    names = {f.name.lower(): int(f) for f in CommFault}
    if isinstance(value, str) and value in names:
        return names[value]
    if isinstance(value, int) and not isinstance(value, bool) and value in names.values():
        return value
    raise where.fail(key, f"must be 0..{max(CommFault)} or one of {', '.join(names)}, got {value!r}")


def _restore(ev: Event) -> Event:
    """The event that ends a ``comm`` event with a ``duration``: fault and delay back to 0."""
    end = ev.at + dict(ev.params)["duration"]
    return Event(end, "comm", (("fault", 0), ("delay_ms", 0.0)), (("comm_fault", 0), ("comm_delay_ms", 0)),
                 f"end of the communication fault of line {ev.line}", ev.line)


#: comm_fault values under which the unit does not carry out the player's own writes
_SILENCING: Final = frozenset({CommFault.NO_RESPONSE, CommFault.BUSY, CommFault.FAILURE, CommFault.CLOSE})


def _check_outages(events: list[Event], source: str) -> None:
    """Refuse an event scheduled while a ``comm`` event keeps the unit from carrying out requests: the
    player writes over Modbus too, and only the unit registers answer during such a fault."""
    since: Event | None = None
    for ev in events:
        if ev.kind == "comm":
            since = ev if dict(ev.writes)["comm_fault"] in _SILENCING else None
        elif since is not None:
            raise ScenarioError(f"{source}:{ev.line}: a {ev.kind} event at {ev.at:g} s falls inside the "
                                f"communication fault set at {since.at:g} s (line {since.line}), when the unit "
                                f"carries out no write; move it, or end the fault first")


# --- the file -----------------------------------------------------------------------------------------

def _device(value: Any, where: _Where, base: Path) -> ServerConfig:
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


def parse_scenario(text: str, *, source: str = "<scenario>", base: Path | None = None) -> Scenario:
    """Parse and check a scenario given as text; ``base`` is where relative ``device`` paths start."""
    data, lines = _load_yaml(text, source)
    where = _Where(source, lines)
    if not isinstance(data, Mapping):
        raise ScenarioError(f"{source}:1: a scenario is a mapping with at least device, duration and events")
    for k in data:
        if k not in _TOP:
            raise where.fail(str(k), f"unknown key (allowed: {', '.join(_TOP)})")
    for k in ("device", "duration", "events"):
        if k not in data:
            raise ScenarioError(f"{source}:1: missing key {k!r}")
    config = _device(data["device"], where, base if base is not None else Path("."))
    units = [lp.device.unit for lp in config.loops]
    if "unit" in data:
        unit = data["unit"]
        if isinstance(unit, bool) or unit not in units:
            raise where.fail("unit", f"the device has no loop on unit {unit!r} (units: {units})")
    elif len(units) == 1:
        unit = units[0]
    else:
        raise ScenarioError(f"{source}:1: the device has several loops (units {units}); say which: unit: N")
    index = units.index(unit)
    loop = config.loops[index]
    duration = _number(data["duration"], "duration", where, lo=0.0)
    if duration <= 0:
        raise where.fail("duration", "must be > 0 s")
    time_scale = _number(data.get("time_scale", 1.0), "time_scale", where, lo=0.0)
    if time_scale <= 0:
        raise where.fail("time_scale", "must be > 0")
    raw_events = data["events"]
    if not isinstance(raw_events, list):
        raise where.fail("events", "must be a list of events")
    scaling = Scaling.from_config(config)
    events: list[Event] = []
    for i, m in enumerate(raw_events):
        ev = _event(m, f"events[{i}]", where, loop, scaling, index)
        if events and ev.at < events[-1].at:
            raise where.fail(f"events[{i}].at", f"time goes backwards: {ev.at:g} s after {events[-1].at:g} s "
                                                f"(line {events[-1].line}); list events in time order")
        if ev.at > duration:
            raise where.fail(f"events[{i}].at", f"{ev.at:g} s is after the end of the scenario "
                                                f"(duration {duration:g} s)")
        events.append(ev)
    ends = [_restore(ev) for ev in events if ev.kind == "comm" and "duration" in dict(ev.params)]
    for ev in ends:
        if ev.at > duration:
            raise ScenarioError(f"{source}:{ev.line}: the communication fault ends at {ev.at:g} s, after the end "
                                f"of the scenario (duration {duration:g} s)")
    events = sorted(events + ends, key=lambda ev: ev.at)   # stable: file order among events at one time
    _check_outages(events, source)
    name, description = data.get("name", Path(source).stem), data.get("description", "")
    for key, value in (("name", name), ("description", description)):
        if not isinstance(value, str):
            raise where.fail(key, f"must be text, got {value!r}")
    return Scenario(name, description.strip(), source, config, unit, duration, time_scale, tuple(events))


def load_scenario(path: str | Path) -> Scenario:
    """Read and check a scenario file (see the module docstring); :class:`ScenarioError` names the line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}:1: cannot read the scenario: {exc}") from None
    return parse_scenario(text, source=str(path), base=path.parent)
