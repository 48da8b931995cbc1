"""Instructor malfunctions: faults injected into one loop at once or ramped over a simulated duration.

:class:`Kind` and :data:`KINDS` are the one list of fault kinds: the station's ``POST /api/malfunctions``,
the scenario files' ``malfunction:`` events (:mod:`valve_emulator.scenario`) and the testing kit's
``inject(kind, ...)`` all take these names and parameters, checked here.

A malfunction request is a mapping ``{"unit", "kind", ...parameters, "ramp": seconds}`` (the HTTP API's body,
a scenario's event). :func:`parse_malfunction` checks it completely -- the kind, every parameter's presence,
type and range -- before anything changes, and raises :class:`MalfunctionError` naming the field. The value
ranges of the quantities the register map also carries (``S``, ``J``, ``load``, ``noise``) are the register
map's own: the check encodes the target as the register words and runs the Modbus write check on them
(:func:`~valve_emulator.device.registers.decode_write` with instructor permission), so the HTTP station can
do nothing an instructor's Modbus write could not.

==============  =====================================  ==========================================
kind            parameters                             effect
==============  =====================================  ==========================================
stiction        ``S``, ``J`` (% travel; either/both)   stiction grows (or is cured) to S, J
seize           --                                     the valve sticks completely
release         --                                     the seized valve moves again
load            ``flow`` (% flow, -100..100)           load disturbance step (or ramp) to ``flow``
noise           ``std`` (PV units)                     PV measurement noise
sensor_stuck    ``value`` (PV units; default: now)     the transmitter shows ``value`` whatever PV does
sensor_drift    ``bias`` (PV units, finite)            the transmitter reads ``bias`` off
comm            ``fault`` (0..5 or a CommFault name),  the unit's communication faults (its
                ``delay_ms`` (0..10000; either/both)   ``comm_fault``, ``comm_delay_ms``)
clear           --                                     all of the above back to the loop's config
==============  =====================================  ==========================================

Ramps (``ramp`` > 0 simulated seconds; only for the kinds with a level: stiction, load, noise,
sensor_drift) interpolate linearly from the value when the malfunction starts, ``x_0``, to the target ``x_1``:

.. math:: x(t) = x_0 + (x_1 - x_0)\\,\\min\\!\\left(1, \\frac{t - t_0}{T_{ramp}}\\right),

evaluated at every tick before the loops step, so the target is reached exactly at ``t_0 + T_ramp``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from enum import StrEnum
from typing import Any

from valve_emulator.device.registers import (
    MAX_DELAY_MS,
    CommFault,
    DataType,
    RegisterError,
    RegisterValueError,
    Scaling,
    address_of,
    decode_write,
    register,
)
from valve_emulator.device.registers.codec import decode_value, write_range
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.errors import UserError

__all__ = ["KINDS", "REGISTER_OF", "FaultKind", "Kind", "Malfunction", "MalfunctionBank", "MalfunctionError",
           "parse_malfunction", "register_word"]


def register_word(name: str, value: float, scaling: Scaling, index: int) -> int:
    """The word a client would write to the linear 16-bit register ``name`` for the physical ``value``.

    Unlike the read encoding this does not clip to the register's range: an out-of-range value that one word
    can carry gives an out-of-range word, which :func:`~valve_emulator.device.registers.decode_write` then
    refuses with the register map's own message. A value no word can carry (``1e308``, or ``-1`` for an
    unsigned register) raises :class:`~valve_emulator.device.registers.RegisterValueError` here, naming the
    register and its range in physical units: clipping it to the word would turn it into a valid write.
    """
    reg = register(name)
    v0, v1 = decode_value(reg, 0, scaling, index), decode_value(reg, 1, scaling, index)
    raw = (value - v0) / (v1 - v0)
    word_lo, word_hi = (-32768, 32767) if reg.type is DataType.INT16 else (0, 65535)
    if not word_lo - 0.5 <= raw < word_hi + 0.5:   # also False for a NaN
        lo, hi = (decode_value(reg, r, scaling, index) for r in write_range(reg, scaling, index))
        raise RegisterValueError(f"register {reg.name}: {value:g} out of range {lo:g}..{hi:g}", register=reg.name,
                                 allowed=write_range(reg, scaling, index))
    return round(raw) & 0xFFFF


class Kind(StrEnum):
    """The fault kinds: the one list the station, the scenario files and the testing kit's ``inject`` use."""

    STICTION = "stiction"
    SEIZE = "seize"
    RELEASE = "release"
    LOAD = "load"
    NOISE = "noise"
    SENSOR_STUCK = "sensor_stuck"
    SENSOR_DRIFT = "sensor_drift"
    COMM = "comm"
    CLEAR = "clear"


@dataclass(frozen=True)
class FaultKind:
    """What a fault kind takes: its parameters (``one_of``: at least one of the optional ones is needed),
    whether it may ramp, and the register each parameter is checked against (and written to over Modbus)."""

    required: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()
    one_of: bool = False
    ramped: bool = False

    @property
    def parameters(self) -> tuple[str, ...]:
        return self.required + self.optional


#: Every fault kind and its parameters (the table of the module docstring). A new kind is a row here, a
#: branch in :meth:`MalfunctionBank.inject` and, if the register map carries it, one in the scenario's
#: register form (:func:`valve_emulator.scenario.player.register_writes`).
KINDS: dict[Kind, FaultKind] = {
    Kind.STICTION: FaultKind(optional=("S", "J"), one_of=True, ramped=True),
    Kind.SEIZE: FaultKind(),
    Kind.RELEASE: FaultKind(),
    Kind.LOAD: FaultKind(required=("flow",), ramped=True),
    Kind.NOISE: FaultKind(required=("std",), ramped=True),
    Kind.SENSOR_STUCK: FaultKind(optional=("value",)),
    Kind.SENSOR_DRIFT: FaultKind(required=("bias",), ramped=True),
    Kind.COMM: FaultKind(optional=("fault", "delay_ms"), one_of=True),
    Kind.CLEAR: FaultKind(),
}
#: parameter -> register that carries it (range checked by the register map)
REGISTER_OF = {"S": "S", "J": "J", "flow": "load", "std": "noise", "fault": "comm_fault",
               "delay_ms": "comm_delay_ms"}


class MalfunctionError(UserError):
    """A malfunction request that cannot be applied; ``field`` names the offending key."""

    def __init__(self, message: str, *, field: str) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True, kw_only=True)
class Malfunction:
    """One checked malfunction of loop ``index`` (bank order) at unit ``unit``."""

    unit: int
    index: int
    kind: Kind
    params: dict[str, float]
    ramp: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"unit": self.unit, "kind": str(self.kind), **self.params, "ramp": self.ramp}


def _whole(value: float | None) -> int | None:
    return None if value is None else int(value)


def _number(body: Mapping[str, Any], key: str) -> float:
    value = body[key]
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise MalfunctionError(f"field {key!r} must be a finite number, got {value!r}", field=key)
    return float(value)


def parse_malfunction(body: Any, *, unit_index: Mapping[int, int], scaling: Scaling) -> Malfunction:
    """Check a request mapping completely (see the module docstring); raise :class:`MalfunctionError`."""
    if not isinstance(body, Mapping):
        raise MalfunctionError(f"request body: a malfunction must be a JSON object, got {type(body).__name__}",
                               field="body")
    for key in ("unit", "kind"):
        if key not in body:
            raise MalfunctionError(f"field {key!r} is required", field=key)
    unit = body["unit"]
    if isinstance(unit, bool) or not isinstance(unit, int) or unit not in unit_index:
        raise MalfunctionError(f"field 'unit': no loop at unit {unit!r} (units {sorted(unit_index)})", field="unit")
    try:
        kind = Kind(body["kind"])
    except (ValueError, TypeError):
        raise MalfunctionError(f"field 'kind': unknown malfunction {body['kind']!r}; one of "
                               f"{', '.join(k.value for k in Kind)}", field="kind") from None
    spec = KINDS[kind]
    for key in body:
        if key not in ("unit", "kind", "ramp", *spec.parameters):
            raise MalfunctionError(f"field {key!r} is not a parameter of {kind.value} (it takes "
                                   f"{', '.join(spec.parameters) or 'none'}, and ramp)", field=key)
    for key in spec.required:
        if key not in body:
            raise MalfunctionError(f"field {key!r} is required for {kind.value}", field=key)
    if spec.one_of and not set(spec.optional) & set(body):
        first, second = spec.optional
        raise MalfunctionError(f"{kind.value} needs field {first!r} or {second!r} (or both)", field=first)
    params = {key: _number(body, key) if key != "fault" else _comm_fault(body[key])
              for key in spec.parameters if key in body}
    if kind is Kind.COMM:
        _check_comm(params)
    ramp = _number(body, "ramp") if "ramp" in body else 0.0
    if ramp < 0:
        raise MalfunctionError(f"field 'ramp' must be >= 0 s, got {ramp!r}", field="ramp")
    if ramp > 0 and not spec.ramped:
        ramped = sorted(k.value for k, s in KINDS.items() if s.ramped)
        raise MalfunctionError(f"field 'ramp': {kind.value} happens at once; ramps are for "
                               f"{', '.join(ramped)}", field="ramp")
    index = unit_index[unit]
    for key, value in params.items():
        reg_name = REGISTER_OF.get(key)
        if reg_name is None or kind is Kind.COMM:   # comm: checked above, with the fault's names
            continue
        try:
            word = register_word(reg_name, value, scaling, index)
            decode_write(address_of(reg_name), [word], scaling, index, role=INSTRUCTOR)
        except RegisterError as exc:
            raise MalfunctionError(f"field {key!r}: {exc}", field=key) from None
    return Malfunction(unit=unit, index=index, kind=kind, params=params, ramp=ramp)


def _comm_fault(value: Any) -> float:
    """A ``fault`` given as its number or as the name of a :class:`CommFault` (``busy``)."""
    names = {f.name.lower(): float(f) for f in CommFault}
    if isinstance(value, str):
        if value not in names:
            raise MalfunctionError(f"field 'fault' must be 0..{max(CommFault)} or one of {', '.join(names)}, "
                                   f"got {value!r}", field="fault")
        return names[value]
    return _number({"fault": value}, "fault")


def _check_comm(params: Mapping[str, float]) -> None:
    """A communication fault: ``fault`` one of :class:`CommFault`, ``delay_ms`` 0..MAX_DELAY_MS (whole ms)."""
    allowed = {"fault": (min(CommFault), max(CommFault)), "delay_ms": (0, MAX_DELAY_MS)}
    for key, value in params.items():
        lo, hi = allowed[key]
        if value != int(value) or not lo <= value <= hi:
            names = ", ".join(f"{int(f)} {f.name.lower()}" for f in CommFault) if key == "fault" else "ms"
            raise MalfunctionError(f"field {key!r} must be a whole number {lo}..{hi} ({names}), got {value:g}",
                                   field=key)


_QUANTITIES = ("S", "J", "load", "noise", "bias")


@dataclass(kw_only=True)
class _Ramp:
    index: int
    quantity: str          # S, J, load, noise, bias
    start: float
    target: float
    t0: float
    duration: float

    def value(self, t: float) -> float:
        frac = 1.0 if self.duration <= 0 else min(1.0, max(0.0, (t - self.t0) / self.duration))
        return self.target if frac >= 1.0 else self.start + (self.target - self.start) * frac


class MalfunctionBank:
    """The active ramps of a loop bank and the log of applied malfunctions.

    :meth:`inject` applies an immediate malfunction at once and registers a ramp otherwise; :meth:`apply`
    (called by the device at each tick, before the step) sets every ramped quantity for time ``t``.
    """

    def __init__(self, bank: Any) -> None:
        self.bank = bank
        #: the Modbus server's communication faults (:class:`~valve_emulator.device.comm.CommFaults`), handed
        #: over by the server that serves this device; without one a ``comm`` malfunction is refused
        self.comm: Any = None
        self._ramps: dict[tuple[int, str], _Ramp] = {}
        #: applied malfunctions, oldest first: ``(simulated time, Malfunction)``
        self.log: list[tuple[float, Malfunction]] = []
        # the loops' configured values, for ``clear``
        self._base = {"S": bank.S.copy(), "J": bank.J.copy(), "noise": bank.noise_std.copy()}

    def _get(self, i: int, quantity: str) -> float:
        b = self.bank
        return float({"S": b.S, "J": b.J, "load": b.load, "noise": b.noise_std, "bias": b.pv_bias}[quantity][i])

    def _set(self, i: int, quantity: str, value: float) -> None:
        b = self.bank
        if quantity in ("S", "J"):
            b.set_valve(i, **{quantity: value})
        elif quantity == "load":
            b.set_load(i, value)
        elif quantity == "noise":
            b.set_noise(i, max(value, 0.0))
        else:
            b.set_sensor(i, bias=value)

    def inject(self, m: Malfunction, t: float) -> None:
        """Apply ``m`` starting at simulated time ``t``."""
        i, b = m.index, self.bank
        levels = {"S": "S", "J": "J", "flow": "load", "std": "noise", "bias": "bias"}
        if m.kind is Kind.SEIZE:
            b.set_frozen(i, True)
        elif m.kind is Kind.RELEASE:
            b.set_frozen(i, False)
        elif m.kind is Kind.SENSOR_STUCK:
            b.set_sensor(i, stuck=m.params.get("value", float(b.pv[i])))
        elif m.kind is Kind.COMM:
            if self.comm is None:
                raise MalfunctionError("comm: this device is not served over Modbus here", field="kind")
            self.comm.set(m.unit, fault=_whole(m.params.get("fault")), delay_ms=_whole(m.params.get("delay_ms")))
        elif m.kind is Kind.CLEAR:
            if self.comm is not None:
                self.comm.set(m.unit, fault=int(CommFault.NONE), delay_ms=0)
            for q in _QUANTITIES:
                self._ramps.pop((i, q), None)
            b.set_valve(i, S=float(self._base["S"][i]), J=float(self._base["J"][i]))
            b.set_noise(i, float(self._base["noise"][i]))
            b.set_load(i, 0.0)
            b.set_frozen(i, False)
            b.set_sensor(i, bias=0.0, release=True)
        else:
            for key, value in m.params.items():
                q = levels[key]
                ramp = _Ramp(index=i, quantity=q, start=self._get(i, q), target=value, t0=t, duration=m.ramp)
                if m.ramp > 0:
                    self._ramps[(i, q)] = ramp
                else:
                    self._ramps.pop((i, q), None)
                    self._set(i, q, value)
        self.log.append((t, m))

    def apply(self, t: float) -> None:
        """Set every ramped quantity for simulated time ``t``; finished ramps end with their target."""
        if not self._ramps:
            return
        done = []
        for key, ramp in self._ramps.items():
            self._set(ramp.index, ramp.quantity, ramp.value(t))
            if t >= ramp.t0 + ramp.duration:
                done.append(key)
        for key in done:
            del self._ramps[key]

    @property
    def ramping(self) -> bool:
        """Is a ramp still running (so every tick must set its quantity)?"""
        return bool(self._ramps)

    @property
    def active(self) -> list[dict[str, Any]]:
        """The ramps still running, for display."""
        return [asdict(r) for r in self._ramps.values()]

    # snapshots: the ramps are part of the state
    def state(self) -> list[dict[str, Any]]:
        return [asdict(r) for r in self._ramps.values()]

    def set_state(self, ramps: list[Any]) -> None:
        """Put back ramps of :meth:`state` (or checked by :meth:`parse_state`)."""
        self._ramps = {(r.index, r.quantity): r for r in self.parse_state(ramps, n=self.bank.n)}

    @staticmethod
    def parse_state(ramps: list[Any], *, n: int) -> list[_Ramp]:
        """Ramps of :meth:`state` (dicts, e.g. read from a snapshot file) checked for a bank of ``n`` loops:
        ``ValueError``/``TypeError``/``KeyError`` naming the entry if one does not fit."""
        out = []
        for k, r in enumerate(ramps):
            ramp = r if isinstance(r, _Ramp) else _Ramp(**r)
            numbers_ok = all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                             for x in (ramp.start, ramp.target, ramp.t0, ramp.duration))
            if not (isinstance(ramp.index, int) and 0 <= ramp.index < n and ramp.quantity in _QUANTITIES
                    and numbers_ok):
                raise ValueError(f"ramps[{k}] = {r!r}: index 0..{n - 1}, quantity one of "
                                 f"{', '.join(_QUANTITIES)} and finite numbers expected")
            out.append(ramp)
        return out
