"""Training scenarios for the instructor station: timed malfunctions (with ramps), triggers, hints, scoring.

A training scenario is YAML (or the same mapping as JSON)::

    name: sticky_valve_lesson
    notes: |                                   # shown to the instructor only
      The valve starts to stick at 30 s. Expect the trainee to go to manual within a minute.
    limits: {1: [-8, 8]}                       # alarm and scoring limits per unit (PV units)
    events:                                    # at simulated seconds from the start
      - {at: 30, malfunction: {unit: 1, kind: stiction, S: 8, J: 3, ramp: 60}, say: "packing binds"}
    triggers:                                  # each fires once, when its condition first holds
      - id: cycling
        when: {pv_outside: {unit: 1, band: [-2, 2], for: 20}}   # PV outside the band for 20 s on end
        do: {hint: shape}                      # or {say: text}, or {malfunction: {...}}
      - id: operator_reacted
        when: {manual: {unit: 1}}              # the trainee put the loop in manual
        do: {say: "trainee switched to manual"}
      - id: late
        when: {since_malfunction: {unit: 1, after: 120}}   # 120 s after a malfunction on unit 1
        do: {malfunction: {unit: 1, kind: seize}}
      - id: acked
        when: {acknowledged: {unit: 1}}        # the trainee acknowledged an alarm
        do: {say: "alarm acknowledged"}
    hints:                                     # released by the instructor (or a trigger); each costs points
      - {id: shape, text: "Compare the shapes of OP and PV."}
    scoring: {iae: 1.0, outside: 1.0, response: 1.0, hint: 10.0}   # penalty weights

:func:`parse_training` checks the structure and raises :class:`~valve_emulator.scenario.timeline.ScenarioError`
naming the key (``events[0].at: must be >= 0``); the malfunctions themselves are checked against the device
when the station loads the scenario. Pure: no device, no clock.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import yaml

from valve_emulator.scenario.timeline import ScenarioError

__all__ = ["Condition", "Trigger", "TrainingScenario", "TimedEvent", "parse_training"]


class Condition(StrEnum):
    PV_OUTSIDE = "pv_outside"
    MANUAL = "manual"
    ACKNOWLEDGED = "acknowledged"
    SINCE_MALFUNCTION = "since_malfunction"


@dataclass(frozen=True, kw_only=True)
class TimedEvent:
    at: float
    action: dict[str, Any]       # {"malfunction": {...}} | {"say": text} | {"hint": id}
    say: str = ""


@dataclass(frozen=True, kw_only=True)
class Trigger:
    id: str
    condition: Condition
    unit: int
    band: tuple[float, float] = (-math.inf, math.inf)
    duration: float = 0.0        # pv_outside: for; since_malfunction: after
    action: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class TrainingScenario:
    name: str
    notes: str
    limits: dict[int, tuple[float, float]]
    events: tuple[TimedEvent, ...]
    triggers: tuple[Trigger, ...]
    hints: dict[str, str]
    scoring: dict[str, float]
    expert: dict[str, Any] | None = None


_TOP = ("name", "notes", "limits", "events", "triggers", "hints", "scoring", "expert")
_SCORING = ("iae", "outside", "response", "hint")


def _fail(key: str, message: str) -> ScenarioError:
    return ScenarioError(f"scenario: {key}: {message}")


def _num(value: Any, key: str, lo: float = -math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) or value < lo:
        raise _fail(key, f"must be a finite number{'' if lo == -math.inf else f' >= {lo:g}'}, got {value!r}")
    return float(value)


def _unit(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
        raise _fail(key, f"must be a unit id 0..255, got {value!r}")
    return value


def _mapping(value: Any, key: str) -> dict:
    if not isinstance(value, dict):
        raise _fail(key, f"must be a mapping, got {type(value).__name__}")
    return value


def _action(value: Any, key: str, hints: dict[str, str]) -> dict[str, Any]:
    m = _mapping(value, key)
    if len(m) != 1 or next(iter(m)) not in ("malfunction", "say", "hint"):
        raise _fail(key, f"must be one of {{malfunction: ...}}, {{say: text}}, {{hint: id}}, got {value!r}")
    (kind, arg), = m.items()
    if kind == "malfunction":
        _mapping(arg, f"{key}.malfunction")
    elif kind == "hint" and arg not in hints:
        raise _fail(f"{key}.hint", f"no hint with id {arg!r} (hints: {', '.join(hints) or 'none'})")
    elif kind == "say" and not isinstance(arg, str):
        raise _fail(f"{key}.say", f"must be text, got {arg!r}")
    return {kind: arg}


def _trigger(value: Any, key: str, hints: dict[str, str]) -> Trigger:
    m = _mapping(value, key)
    for k in m:
        if k not in ("id", "when", "do"):
            raise _fail(f"{key}.{k}", "unknown key (a trigger has id, when, do)")
    tid = m.get("id")
    if not isinstance(tid, str) or not tid:
        raise _fail(f"{key}.id", f"must be a non-empty text, got {tid!r}")
    when = _mapping(m.get("when"), f"{key}.when")
    if len(when) != 1:
        raise _fail(f"{key}.when", f"must hold one condition of {', '.join(c.value for c in Condition)}")
    (name, args), = when.items()
    try:
        cond = Condition(name)
    except ValueError:
        raise _fail(f"{key}.when.{name}", f"unknown condition; one of {', '.join(c.value for c in Condition)}") \
            from None
    args = _mapping(args, f"{key}.when.{name}")
    where = f"{key}.when.{name}"
    allowed = {Condition.PV_OUTSIDE: ("unit", "band", "for"), Condition.SINCE_MALFUNCTION: ("unit", "after")}.get(
        cond, ("unit",))
    for k in args:
        if k not in allowed:
            raise _fail(f"{where}.{k}", f"unknown key (takes {', '.join(allowed)})")
    unit = _unit(args.get("unit"), f"{where}.unit")
    band, duration = (-math.inf, math.inf), 0.0
    if cond is Condition.PV_OUTSIDE:
        b = args.get("band")
        if not (isinstance(b, list) and len(b) == 2):
            raise _fail(f"{where}.band", f"must be [low, high], got {b!r}")
        band = (_num(b[0], f"{where}.band[0]"), _num(b[1], f"{where}.band[1]"))
        if band[0] >= band[1]:
            raise _fail(f"{where}.band", f"low must be below high, got {b!r}")
        duration = _num(args.get("for", 0.0), f"{where}.for", 0.0)
    elif cond is Condition.SINCE_MALFUNCTION:
        duration = _num(args.get("after"), f"{where}.after", 0.0)
    return Trigger(id=tid, condition=cond, unit=unit, band=band, duration=duration,
                   action=_action(m.get("do"), f"{key}.do", hints))


#: Limits on scenario YAML text, far above any lesson's (a few kB, nested three or four deep). PyYAML's
#: pure-Python parser takes time quadratic in the nesting of flow collections (``[[[[...``: 2 s for 3,000),
#: and the station parses in its event loop, so text beyond them is refused before parsing.
MAX_YAML_CHARS = 64 * 1024
MAX_FLOW_DEPTH = 64


def _check_yaml_text(text: str) -> None:
    """Refuse YAML text longer than :data:`MAX_YAML_CHARS` or nesting ``[``/``{`` deeper than
    :data:`MAX_FLOW_DEPTH` (counted with brackets inside quotes too: a lesson never comes near)."""
    if len(text) > MAX_YAML_CHARS:
        raise ScenarioError(f"scenario: YAML text of {len(text)} characters; at most {MAX_YAML_CHARS}")
    depth = deepest = 0
    for opened in (ch in "[{" for ch in text if ch in "[]{}"):
        depth = depth + 1 if opened else max(0, depth - 1)
        deepest = max(deepest, depth)
        if deepest > MAX_FLOW_DEPTH:
            raise ScenarioError(f"scenario: YAML nested too deeply (more than {MAX_FLOW_DEPTH} levels of [ or {{)")


def parse_training(data: Any) -> TrainingScenario:
    """Check a training scenario mapping (or YAML text); see the module docstring."""
    if isinstance(data, str):
        _check_yaml_text(data)
        try:
            data = yaml.safe_load(data)
        except yaml.YAMLError as exc:
            raise ScenarioError(f"scenario: YAML syntax error: {exc}") from None
        except RecursionError:
            raise ScenarioError("scenario: YAML nested too deeply") from None
    m = _mapping(data, "scenario")
    for k in m:
        if k not in _TOP:
            raise _fail(k, f"unknown key (a training scenario has {', '.join(_TOP)})")
    hints = {}
    for i, h in enumerate(m.get("hints") or []):
        h = _mapping(h, f"hints[{i}]")
        if not isinstance(h.get("id"), str) or not isinstance(h.get("text"), str):
            raise _fail(f"hints[{i}]", "needs id and text")
        hints[h["id"]] = h["text"]
    limits = {}
    for u, lim in _mapping(m.get("limits") or {}, "limits").items():
        unit = _unit(u, f"limits.{u}")
        if not (isinstance(lim, list) and len(lim) == 2):
            raise _fail(f"limits.{u}", f"must be [low, high], got {lim!r}")
        lo, hi = _num(lim[0], f"limits.{u}[0]"), _num(lim[1], f"limits.{u}[1]")
        if lo >= hi:
            raise _fail(f"limits.{u}", f"low must be below high, got {lim!r}")
        limits[unit] = (lo, hi)
    events, last = [], 0.0
    for i, e in enumerate(m.get("events") or []):
        e = _mapping(e, f"events[{i}]")
        at = _num(e.get("at"), f"events[{i}].at", 0.0)
        if at < last:
            raise _fail(f"events[{i}].at", f"times must not go backwards ({at:g} after {last:g})")
        last = at
        say = e.get("say", "")
        rest = {k: v for k, v in e.items() if k not in ("at", "say")}
        events.append(TimedEvent(at=at, action=_action(rest, f"events[{i}]", hints), say=str(say)))
    triggers = tuple(_trigger(t, f"triggers[{i}]", hints) for i, t in enumerate(m.get("triggers") or []))
    ids = [t.id for t in triggers]
    if len(set(ids)) != len(ids):
        raise _fail("triggers", f"trigger ids must be unique, got {ids}")
    scoring = {}
    for k, v in _mapping(m.get("scoring") or {}, "scoring").items():
        if k not in _SCORING:
            raise _fail(f"scoring.{k}", f"unknown weight (one of {', '.join(_SCORING)})")
        scoring[k] = _num(v, f"scoring.{k}", 0.0)
    expert = m.get("expert")
    if expert is not None:
        _mapping(expert, "expert")
    return TrainingScenario(name=str(m.get("name", "scenario")), notes=str(m.get("notes", "")), limits=limits,
                            events=tuple(events), triggers=triggers, hints=hints, scoring=scoring, expert=expert)
