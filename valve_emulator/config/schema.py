"""Typed, frozen configuration objects: the one place that documents every key.

Every YAML key of a configuration file is listed in :data:`KEYS` (by section) and documented next to the
dataclass field it fills. Field-level rules (types, ranges, monotone tables, a proper transfer function)
live in each class's ``__post_init__``, so they hold for every instance — whether built by the loader,
by hand, or by ``dataclasses.replace`` for an override — and a rejected value raises :class:`ConfigError`
naming the key. The loader (:mod:`valve_emulator.config.loader`) adds the file, the dotted path and the
line number to that message.

Conventions (see ``docs/design.md``): OP, MV and flow are in % of valve travel; PV in engineering units;
times in seconds; the stiction parameters ``S`` (deadband + stickband, OP axis) and ``J`` (slip jump, MV
axis) use the 2005 convention of Choudhury, Thornhill & Shah, *Control Engineering Practice* 13 (2005)
641–658. The 2003 paper (Choudhury, Thornhill & Shah, ADCHEM 2003) prints ``s, j`` with ``S = s`` and
``J = 2 j``; the loader accepts
that form as ``seed_s``/``seed_j`` and keeps what was typed in :attr:`ValveConfig.seed_form`.
"""

from __future__ import annotations

import ipaddress
import math
import numbers
from dataclasses import KW_ONLY, dataclass, fields
from enum import StrEnum
from typing import Any

from valve_emulator.config.roles import RoleConfigError, custom_roles
from valve_emulator.errors import UserError
from valve_emulator.physics.signal_chain import CHARACTERISTICS, DEFAULT_MA_TABLE, DEFAULT_RANGEABILITY
from valve_emulator.physics.stiction import MODELS, seed_to_2005

__all__ = [
    "ACTIONS", "BLOCK_STRIDE", "CHARACTERISTICS", "DISTURBANCES", "KEYS", "MAX_BLOCKS", "MAX_UNIT", "MODELS",
    "MODES", "WORD_ORDERS", "WordOrder",
    "ConfigError", "ControllerConfig", "DeviceConfig", "DisturbanceConfig", "LoopConfig", "PlantConfig",
    "OpcUaConfig", "OPCUA_POLICIES", "ServerConfig", "SimulationConfig", "TlsConfig", "ValveConfig",
]

DISTURBANCES = ("none", "step", "sine", "random_walk")
ACTIONS = ("reverse", "direct")
MODES = ("auto", "manual")


class WordOrder(StrEnum):
    """Order of the two 16-bit words of a 32-bit register value (``uint32``, ``float32``) on the wire.

    Defined here, below the device, because a configuration names it (``device.word_order``); the register
    map (:mod:`valve_emulator.device.registers`) and the clients use this one definition.
    """

    ABCD = "ABCD"   # high word at the lower address (mbpoll -B); the emulator's default
    CDAB = "CDAB"   # low word first (mbpoll's default)


WORD_ORDERS = tuple(WordOrder)
MAX_UNIT = 247  # highest Modbus unit (slave) id a server may answer as
# Address space of one unit id: every loop behind it owns a block of BLOCK_STRIDE registers (the register
# map plus a pad), and the blocks fill the 16-bit address space. The register map takes both from here,
# because a configuration is validated against them (fleet.loops_per_unit, device.block).
BLOCK_STRIDE = 32
MAX_BLOCKS = 0x10000 // BLOCK_STRIDE

_LOOP_SECTIONS = ("name", "description", "valve", "plant", "controller", "simulation")
_DEVICE = ("unit", "tick", "word_order", "instructor_writes", "instructor_hosts", "read_only",
           "max_connections", "idle_timeout", "frame_timeout", "error_rate", "lockstep", "register_map",
           "roles")

#: Allowed YAML keys per section ("" = top level of a single-loop file, "server" = top level of a
#: multi-loop file). Anything else is an error naming the key.
KEYS: dict[str, tuple[str, ...]] = {
    "": _LOOP_SECTIONS + ("device",),
    "valve": ("model", "S", "J", "seed_s", "seed_j", "rest_time", "initial_direction", "op0", "mv0", "stuck0",
              "actuator_lag", "characteristic", "rangeability", "flow_limits", "ma_table", "op_range"),
    "plant": ("num", "den", "delay", "fopdt", "integrator", "pv0", "u0", "rest_flow", "pv_range", "units",
              "disturbance", "noise", "alarms"),
    "plant.fopdt": ("gain", "tau", "delay"),
    "plant.integrator": ("gain", "delay"),
    # Keys allowed in plant.disturbance depend on its type:
    "plant.disturbance[none]": ("type",),
    "plant.disturbance[step]": ("type", "amplitude", "time"),
    "plant.disturbance[sine]": ("type", "amplitude", "period", "phase"),
    "plant.disturbance[random_walk]": ("type", "std"),
    "controller": ("kc", "ti", "td", "sp", "sp_steps", "bias", "action", "op_limits", "mode"),
    "simulation": ("dt", "duration", "seed"),
    "device": _DEVICE,
    "server": ("device", "loops", "fleet", "opcua", "tls"),
    "opcua": ("port", "policies", "certificate", "private_key", "users", "pki"),
    "tls": ("port", "certificate", "private_key", "ca"),
    "server.device": _DEVICE[1:],
    "loops[i]": _LOOP_SECTIONS + ("unit",),
    "fleet": ("count", "first_unit", "loops_per_unit", "seed", "base", "vary"),
    "fleet.base": _LOOP_SECTIONS,
    "fleet.vary": ("S", "J", "gain", "delay"),
}


class ConfigError(UserError):
    """A configuration value, key or file is wrong.

    ``str(err)`` reads ``"<source>:<line>: <message>"`` (``line`` when known), where the message names
    the dotted key, e.g. ``configs/x.yaml:7: plant.delay must be >= 0, got -3``.

    Parameters
    ----------
    detail : str
        The message; the literal ``{key}`` in it is replaced by `key`.
    key : str
        Dotted key the message is about (``"loops[2].valve.S"``); relative keys are prefixed by the loader.
    source, line : optional
        File name (or ``"<mapping>"``) and 1-based line, as an editor shows it.
    """

    def __init__(self, detail: str, *, key: str = "", source: str = "", line: int | None = None):
        self.detail, self.key, self.source, self.line = detail, key, source, line
        message = detail.replace("{key}", key or "configuration")
        where = f"{source}:{line}: " if source and line else (f"{source}: " if source else "")
        super().__init__(where + message)


# --- value checks: return the normalised value or raise ConfigError naming `key` ----------------------

def _show(value: Any) -> str:
    """How a bad value is quoted in a message (YAML words, not Python's)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, str):
        return f"{value!r} (text)"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    return repr(value)


def real(value: Any, key: str, *, gt: float | None = None, ge: float | None = None,
         le: float | None = None, none_ok: bool = False) -> float | None:
    """A finite float; an int is accepted, a bool is not (``true`` is not a number)."""
    if value is None and none_ok:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        hint = ""
        if isinstance(value, str):
            try:
                float(value)
                # PyYAML follows YAML 1.1, which reads 1e3 (no dot) as text.
                hint = " (YAML reads numbers like 1e3 as text; write 1.0e+3)"
            except ValueError:
                pass
        raise ConfigError(f"{{key}} must be a number, got {_show(value)}{hint}", key=key)
    x = float(value)
    if not math.isfinite(x):
        raise ConfigError(f"{{key}} must be finite, got {value!r}", key=key)
    for ok, rel, bound in ((gt is None or x > gt, ">", gt), (ge is None or x >= ge, ">=", ge),
                           (le is None or x <= le, "<=", le)):
        if not ok:
            raise ConfigError(f"{{key}} must be {rel} {bound:g}, got {value!r}", key=key)
    return x


def integer(value: Any, key: str, *, ge: int | None = None, le: int | None = None) -> int:
    """An int (a float such as 1.0 or a bool is rejected: counts and ids are exact)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{{key}} must be an integer, got {_show(value)}", key=key)
    if (ge is not None and value < ge) or (le is not None and value > le):
        span = f"in {ge}..{le}" if ge is not None and le is not None else (
            f">= {ge}" if ge is not None else f"<= {le}")
        raise ConfigError(f"{{key}} must be {span}, got {value!r}", key=key)
    return int(value)


def choice(value: Any, key: str, choices: tuple[str, ...]) -> str:
    """One of a fixed set of words."""
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{{key}} must be one of {', '.join(choices)}, got {_show(value)}", key=key)
    return value


def text(value: Any, key: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{{key}} must be text, got {_show(value)}", key=key)
    return value


def boolean(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{{key}} must be true or false, got {_show(value)}", key=key)
    return value


def sequence(value: Any, key: str, *, min_len: int = 0, length: int | None = None) -> tuple:
    """A YAML list (tuple accepted from Python); strings and mappings are not lists."""
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{{key}} must be a list, got {_show(value)}", key=key)
    if length is not None and len(value) != length:
        raise ConfigError(f"{{key}} must have exactly {length} items, got {len(value)}", key=key)
    if len(value) < min_len:
        raise ConfigError(f"{{key}} must have at least {min_len} item(s), got {len(value)}", key=key)
    return tuple(value)


def reals(value: Any, key: str, *, min_len: int = 1) -> tuple[float, ...]:
    return tuple(real(v, f"{key}[{i}]") for i, v in enumerate(sequence(value, key, min_len=min_len)))


def interval(value: Any, key: str) -> tuple[float, float]:
    """``[lo, hi]`` with lo < hi."""
    lo, hi = (real(v, f"{key}[{i}]") for i, v in enumerate(sequence(value, key, length=2)))
    if not lo < hi:
        raise ConfigError(f"{{key}} must be [lo, hi] with lo < hi, got [{lo:g}, {hi:g}]", key=key)
    return lo, hi


def _set(obj: Any, **values: Any) -> None:
    """Store normalised values on a frozen instance (only ever called from ``__post_init__``)."""
    for name, value in values.items():
        object.__setattr__(obj, name, value)


_COPIERS: dict[type, tuple[frozenset[str], Any]] = {}


def derive(obj: Any, **changes: Any) -> Any:
    """A copy of the validated, frozen configuration object ``obj`` with ``changes``, *not* checked again.

    Only for values valid by construction: the fleet's loops, whose draws come from ranges whose corners were
    built (and so checked) with :func:`dataclasses.replace`. ``replace`` runs every ``__post_init__`` check
    again, which was most of the time of expanding a 100,000-loop fleet.
    """
    cls = type(obj)
    known = _COPIERS.get(cls)
    if known is None:
        known = _COPIERS[cls] = _copier(cls)
    if not changes.keys() <= known[0]:
        raise TypeError(f"{cls.__name__} has no field(s) {sorted(changes.keys() - known[0])}")
    return known[1](obj, changes)


def _copier(cls: type) -> tuple[frozenset[str], Any]:
    """The field names of the frozen, slotted dataclass ``cls`` and a function ``copy(obj, changes)`` that
    builds a new instance field by field through the slot descriptors (what ``dataclasses`` itself does for
    ``__init__``: one straight line per field, generated once per class, a third of the time of a loop)."""
    names = [f.name for f in fields(cls)]
    lines = ["def copy(obj, changes):", "    new = new_object(cls)"]
    scope: dict[str, Any] = {"new_object": object.__new__, "cls": cls}
    for k, name in enumerate(names):
        scope[f"get{k}"], scope[f"set{k}"] = cls.__dict__[name].__get__, cls.__dict__[name].__set__
        lines.append(f"    set{k}(new, changes[{name!r}] if {name!r} in changes else get{k}(obj))")
    lines.append("    return new")
    exec("\n".join(lines), scope)   # noqa: S102 - code built from the class's own field names
    return frozenset(names), scope["copy"]


# --- the configuration objects ------------------------------------------------------------------------

@dataclass(frozen=True, slots=True, kw_only=True)
class ValveConfig:
    """The sticky valve and its signal chain (YAML section ``valve``).

    The chain, in signal order: OP → actuator lag (``actuator_lag``) → stiction (``S``, ``J``) → MV →
    characteristic → flow limits (``flow_limits``) → flow. The diagnosis' chain has the same order
    (:mod:`valve_emulator.diagnosis.fit.chain`), so a twin places what it found where the fit had it.
    """

    model: str = "kano"            # stiction state machine: choudhury | kano | he (physics.stiction.MODELS)
    S: float = 0.0                 # % travel, deadband + stickband (2005 convention), >= 0
    J: float = 0.0                 # % travel, slip jump (2005 convention), >= 0
    rest_time: float = 0.5         # s >= 0, OP unchanged this long -> valve at rest (kano only)
    initial_direction: int = 1     # +1 | -1: at rest as if it had just moved this way
    op0: float = 50.0              # % travel in 0..100, OP held before any write / without controller
    mv0: float | None = None       # % travel in 0..100, the valve's position at the start (last moved in
                                   # initial_direction); None: at rest at its initial OP, OP − d(S − J)/2
    stuck0: bool = True            # at the start the valve is stuck (True) or still moving (False)
    actuator_lag: float = 0.0      # s >= 0, the actuator's first-order lag between OP and the friction; 0: none
    characteristic: str = "linear"  # inherent flow characteristic: linear | equal_percentage | quick_opening
    rangeability: float = DEFAULT_RANGEABILITY  # R > 1, used by equal_percentage
    flow_limits: tuple[float, float] = (0.0, 100.0)  # % flow, 0 <= lo < hi <= 100: the flow clipped to them
    ma_table: tuple[tuple[float, float], ...] = DEFAULT_MA_TABLE  # (mA, % travel) points, >= 2
    op_range: tuple[float, float] = (0.0, 100.0)  # a recording's OP at 0 and 100 % travel, in its own units
                                                  # (lo < hi); maps a replayed recording's OP to travel
    seed_form: tuple[float, float] | None = None  # (seed_s, seed_j) as typed, when given in that form

    def __post_init__(self) -> None:
        _set(self, model=choice(self.model, "model", MODELS), S=real(self.S, "S", ge=0),
             J=real(self.J, "J", ge=0), rest_time=real(self.rest_time, "rest_time", ge=0))
        if isinstance(self.initial_direction, bool) or self.initial_direction not in (1, -1):
            raise ConfigError(f"{{key}} must be 1 or -1, got {_show(self.initial_direction)}",
                              key="initial_direction")
        _set(self, initial_direction=int(self.initial_direction),
             op0=real(self.op0, "op0", ge=0, le=100),
             mv0=real(self.mv0, "mv0", ge=0, le=100, none_ok=True), stuck0=boolean(self.stuck0, "stuck0"),
             actuator_lag=real(self.actuator_lag, "actuator_lag", ge=0),
             characteristic=choice(self.characteristic, "characteristic", CHARACTERISTICS),
             rangeability=real(self.rangeability, "rangeability", gt=1),
             flow_limits=_percent_interval(self.flow_limits, "flow_limits"))
        _set(self, ma_table=_ma_table(self.ma_table), op_range=interval(self.op_range, "op_range"))
        if self.seed_form is not None:
            s, j = sequence(self.seed_form, "seed_form", length=2)
            s, j = real(s, "seed_s", ge=0), real(j, "seed_j", ge=0)
            if seed_to_2005(s, j) != (self.S, self.J):  # a stale seed_form would misreport the valve
                raise ConfigError(f"{{key}} ({s:g}, {j:g}) does not match S={self.S:g}, J={self.J:g} "
                                  "(S = seed_s, J = 2*seed_j); set seed_form=None when changing S or J",
                                  key="seed_form")
            _set(self, seed_form=(s, j))


def _percent_interval(value: Any, key: str) -> tuple[float, float]:
    """``[lo, hi]`` with ``0 <= lo < hi <= 100`` (a range of % flow or % travel)."""
    lo, hi = interval(value, key)
    for i, x in enumerate((lo, hi)):
        if not 0.0 <= x <= 100.0:
            raise ConfigError(f"{{key}} must be in 0..100 %, got {x:g}", key=f"{key}[{i}]")
    return lo, hi


def _ma_table(value: Any) -> tuple[tuple[float, float], ...]:
    rows = sequence(value, "ma_table", min_len=2)
    table = []
    for i, row in enumerate(rows):
        ma, pct = sequence(row, f"ma_table[{i}]", length=2)
        table.append((real(ma, f"ma_table[{i}][0]", ge=0), real(pct, f"ma_table[{i}][1]", ge=0, le=100)))
    rising = table[1][1] > table[0][1]  # % may fall with mA (a reverse-acting, air-to-close valve)
    for i in range(1, len(table)):
        (ma0, p0), (ma1, p1) = table[i - 1], table[i]
        if not ma1 > ma0:
            raise ConfigError(f"{{key}} mA must be strictly increasing, got {ma1:g} after {ma0:g}",
                              key=f"ma_table[{i}]")
        if not (p1 > p0 if rising else p1 < p0):
            raise ConfigError(f"{{key}} % travel must be strictly monotone, got {p1:g} after {p0:g}",
                              key=f"ma_table[{i}]")
    return tuple(table)


@dataclass(frozen=True, slots=True, kw_only=True)
class DisturbanceConfig:
    """Load disturbance added to the plant input, in % flow (YAML ``plant.disturbance``).

    ``step``: ``amplitude`` from ``time`` on. ``sine``: ``amplitude·sin(2π t / period + phase)``, phase in
    rad. ``random_walk``: increments with standard deviation ``std·√dt`` (``std`` in % per √s).
    Fields that the type does not use keep their defaults.
    """

    type: str = "none"       # none | step | sine | random_walk
    amplitude: float = 0.0   # % flow (step, sine)
    time: float = 0.0        # s >= 0, when the step happens
    period: float = 0.0      # s > 0 (sine)
    phase: float = 0.0       # rad (sine)
    std: float = 0.0         # % per sqrt(s), >= 0 (random_walk)

    def __post_init__(self) -> None:
        _set(self, type=choice(self.type, "type", DISTURBANCES), amplitude=real(self.amplitude, "amplitude"),
             time=real(self.time, "time", ge=0), phase=real(self.phase, "phase"),
             std=real(self.std, "std", ge=0),
             period=real(self.period, "period", **({"gt": 0} if self.type == "sine" else {"ge": 0})))


@dataclass(frozen=True, slots=True)
class PlantConfig:
    """Process ``G(s) = num(s)/den(s)·e^{-delay·s}`` around an operating point (YAML ``plant``).

    ``pv = pv0 + G(s)·(flow − u0)``; coefficients highest power first (as in ``scipy.signal``). The
    transfer function must be proper (deg num <= deg den) with ``den[0] != 0`` and finite coefficients.
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    _: KW_ONLY
    delay: float = 0.0                  # s >= 0, dead time
    pv0: float = 0.0                    # PV at the operating point, engineering units
    u0: float | None = None             # operating-point flow %, None = the valve's initial flow
    rest_flow: float | None = None      # % flow the plant starts at rest for, None = the valve's initial flow
    pv_range: tuple[float, float] | None = None  # (lo, hi) for scaled registers; None -> pv0 ± 100
    units: str = ""                     # PV engineering units, e.g. "kg/m3"
    disturbance: DisturbanceConfig = DisturbanceConfig()
    noise: float = 0.0                  # measurement noise std, engineering units, >= 0
    alarms: tuple[float, float] | None = None  # PV low/high alarm limits; None: see alarm_limits

    def __post_init__(self) -> None:
        num, den = reals(self.num, "num"), reals(self.den, "den")
        if den[0] == 0:
            raise ConfigError("{key} leading coefficient must be nonzero, got 0", key="den[0]")
        if not any(num):
            raise ConfigError("{key} must not be all zero (a plant with no gain)", key="num")
        order = len(num) - next(i for i, c in enumerate(num) if c != 0) - 1  # leading zeros do not count
        if order > len(den) - 1:
            raise ConfigError(f"{{key}} has degree {order} > degree {len(den) - 1} of den: the transfer "
                              "function must be proper", key="num")
        pv0 = real(self.pv0, "pv0")
        pv_range = (pv0 - 100.0, pv0 + 100.0) if self.pv_range is None else interval(self.pv_range, "pv_range")
        if not isinstance(self.disturbance, DisturbanceConfig):
            raise ConfigError("{key} must be a DisturbanceConfig", key="disturbance")
        alarms = None if self.alarms is None else interval(self.alarms, "alarms")
        _set(self, num=num, den=den, delay=real(self.delay, "delay", ge=0), pv0=pv0,
             u0=real(self.u0, "u0", none_ok=True), rest_flow=real(self.rest_flow, "rest_flow", none_ok=True),
             pv_range=pv_range, units=text(self.units, "units"),
             noise=real(self.noise, "noise", ge=0), alarms=alarms)

    @property
    def alarm_limits(self) -> tuple[float, float]:
        """PV low/high alarm limits: ``alarms`` when given, else 10 % and 90 % of ``pv_range``."""
        if self.alarms is not None:
            return self.alarms
        lo, hi = self.pv_range
        return lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo)


@dataclass(frozen=True, slots=True)
class ControllerConfig:
    """Internal PI(D), ISA parallel-ideal position form (YAML ``controller``).

    ``op = bias + kc·(e + ∫e dt / ti + td·de/dt)``, ``e = sp − pv`` (reverse) or ``pv − sp`` (direct).
    """

    kc: float                       # > 0, % OP per PV unit
    _: KW_ONLY
    ti: float | None = None         # s > 0; None = no integral action (P or PD)
    td: float = 0.0                 # s >= 0
    sp: float = 0.0                 # initial set point, PV units (the loader defaults it to plant.pv0)
    sp_steps: tuple[tuple[float, float], ...] = ()  # (time s, new sp), times >= 0 strictly increasing
    bias: float = 50.0              # % OP at zero error
    action: str = "reverse"         # reverse | direct
    op_limits: tuple[float, float] = (0.0, 100.0)   # % OP, lo < hi
    mode: str = "auto"              # auto | manual: manual holds OP (initially bias) until set to auto

    def __post_init__(self) -> None:
        steps = []
        for i, step in enumerate(sequence(self.sp_steps, "sp_steps")):
            t, sp = sequence(step, f"sp_steps[{i}]", length=2)
            t = real(t, f"sp_steps[{i}][0]", ge=0)
            if steps and not t > steps[-1][0]:
                raise ConfigError(f"{{key}} times must be strictly increasing, got {t:g} after "
                                  f"{steps[-1][0]:g}", key=f"sp_steps[{i}]")
            steps.append((t, real(sp, f"sp_steps[{i}][1]")))
        _set(self, kc=real(self.kc, "kc", gt=0), ti=real(self.ti, "ti", gt=0, none_ok=True),
             td=real(self.td, "td", ge=0), sp=real(self.sp, "sp"), sp_steps=tuple(steps),
             bias=real(self.bias, "bias"), action=choice(self.action, "action", ACTIONS),
             op_limits=interval(self.op_limits, "op_limits"), mode=choice(self.mode, "mode", MODES))


@dataclass(frozen=True, slots=True, kw_only=True)
class SimulationConfig:
    """Offline run settings (YAML ``simulation``)."""

    dt: float = 0.1             # s > 0, sample time
    duration: float = 3000.0    # s > 0 and >= dt
    seed: int = 0               # >= 0, seeds noise and disturbances

    def __post_init__(self) -> None:
        dt, duration = real(self.dt, "dt", gt=0), real(self.duration, "duration", gt=0)
        if duration < dt:
            raise ConfigError(f"{{key}} must be >= dt ({dt:g}), got {self.duration!r}", key="duration")
        _set(self, dt=dt, duration=duration, seed=integer(self.seed, "seed", ge=0))


#: OPC UA security policies (the secure ones always with Sign&Encrypt).
OPCUA_POLICIES = ("None", "Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")


def _optional_path(value: Any, key: str) -> str | None:
    return None if value is None else text(value, key)


@dataclass(frozen=True, slots=True, kw_only=True)
class OpcUaConfig:
    """The OPC UA server beside Modbus (YAML ``opcua``; ``docs/opcua.md``). Paths are relative to the file."""

    port: int | None = None           # 0..65535 (0: a free port); None: no OPC UA server
    policies: tuple[str, ...] = ("None",)   # of OPCUA_POLICIES
    certificate: str | None = None    # application instance certificate (valve-emulator certs --opcua DIR)
    private_key: str | None = None
    users: str | None = None          # users file: names, hashed passwords, roles
    pki: str | None = None            # trust list of client certificates (trusted/certs, rejected/certs)

    def __post_init__(self) -> None:
        policies = tuple(choice(p, f"policies[{i}]", OPCUA_POLICIES)
                         for i, p in enumerate(sequence(self.policies, "policies", min_len=1)))
        _set(self, port=None if self.port is None else integer(self.port, "port", ge=0, le=65535),
             policies=policies, certificate=_optional_path(self.certificate, "certificate"),
             private_key=_optional_path(self.private_key, "private_key"), users=_optional_path(self.users, "users"),
             pki=_optional_path(self.pki, "pki"))


@dataclass(frozen=True, slots=True, kw_only=True)
class TlsConfig:
    """Modbus/TCP Security beside the plain port (YAML ``tls``; ``docs/opcua.md``). Paths relative to the file."""

    port: int | None = None           # 0..65535 (802 by convention; 0: a free port); None: no TLS listener
    certificate: str | None = None    # the server's certificate (PEM)
    private_key: str | None = None
    ca: str | None = None             # the CA that signs client certificates

    def __post_init__(self) -> None:
        _set(self, port=None if self.port is None else integer(self.port, "port", ge=0, le=65535),
             certificate=_optional_path(self.certificate, "certificate"),
             private_key=_optional_path(self.private_key, "private_key"), ca=_optional_path(self.ca, "ca"))
        if self.port is not None:
            for key in ("certificate", "private_key", "ca"):
                if getattr(self, key) is None:
                    raise ConfigError("{key} is required with tls.port (make the files with "
                                      "'valve-emulator certs --modbus DIR')", key=key)


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceConfig:
    """Modbus TCP device settings (YAML ``device``).

    ``unit`` is None only in :attr:`ServerConfig.device` (server-wide settings); every loop carries its
    own unit in ``LoopConfig.device.unit``.
    """

    unit: int | None = 1            # Modbus unit id 1..247
    block: int = 0                  # 0..MAX_BLOCKS-1, the loop's block of BLOCK_STRIDE registers within its
                                    # unit (fleet.loops_per_unit > 1; set by the fleet, not a YAML key)
    tick: float = 0.1               # s > 0, simulated time per tick (= real-time period at time-scale 1)
    word_order: WordOrder = WordOrder.ABCD  # ABCD | CDAB, register order of float32 / uint32 values
    instructor_writes: bool = False  # allow writes to S, J and fault-injection registers
    instructor_hosts: tuple[str, ...] = ()  # client IPs allowed instructor writes (empty = any), normalised
    read_only: bool = False         # refuse every write
    # Connection hygiene: a Modbus TCP server facing unknown clients must not let floods, idle
    # or half-open sockets, or a client trickling one byte a second use up its connections.
    max_connections: int = 64       # 1..65535, simultaneous client connections; more are refused and logged
    idle_timeout: float = 60.0      # s > 0, close a connection that has sent no complete request this long
    frame_timeout: float = 5.0      # s > 0, a request frame must arrive completely within this time
    error_rate: float = 100.0       # > 0, exception answers per s per connection before it is read slower
    lockstep: bool = False          # the clock is the client's: no tick runs until it writes the step register
    register_map: Any = None        # a RegisterMapConfig (config/register_map.py); None: the standard map
    # Custom roles beside viewer, operator and instructor: ((name, writable tags), ...) (config/roles.py)
    roles: tuple[tuple[str, tuple[str, ...]], ...] = ()

    def __post_init__(self) -> None:
        if self.register_map is not None and not hasattr(self.register_map, "tags"):   # the loader parses it
            raise ConfigError(f"{{key}} must be a RegisterMapConfig (config.register_map.parse_register_map), got "
                              f"{_show(self.register_map)}", key="register_map")
        hosts = []
        for i, host in enumerate(sequence(self.instructor_hosts, "instructor_hosts")):
            try:
                hosts.append(str(ipaddress.ip_address(text(host, f"instructor_hosts[{i}]"))))
            except ValueError as exc:
                if isinstance(exc, ConfigError):
                    raise
                raise ConfigError(f"{{key}} must be an IP address, got {host!r}",
                                  key=f"instructor_hosts[{i}]") from None
        _set(self, unit=None if self.unit is None else integer(self.unit, "unit", ge=1, le=MAX_UNIT),
             block=integer(self.block, "block", ge=0, le=MAX_BLOCKS - 1),
             tick=real(self.tick, "tick", gt=0),
             word_order=WordOrder(choice(self.word_order, "word_order", WORD_ORDERS)),
             instructor_writes=boolean(self.instructor_writes, "instructor_writes"),
             instructor_hosts=tuple(hosts), read_only=boolean(self.read_only, "read_only"),
             max_connections=integer(self.max_connections, "max_connections", ge=1, le=65535),
             idle_timeout=real(self.idle_timeout, "idle_timeout", gt=0),
             frame_timeout=real(self.frame_timeout, "frame_timeout", gt=0),
             error_rate=real(self.error_rate, "error_rate", gt=0), lockstep=boolean(self.lockstep, "lockstep"))
        try:
            _set(self, roles=custom_roles(self.roles, "roles"))
        except RoleConfigError as exc:
            raise ConfigError(exc.detail, key=exc.key) from None


def _instance(value: Any, key: str, cls: type, *, none_ok: bool = False) -> None:
    if not (isinstance(value, cls) or (none_ok and value is None)):
        raise ConfigError(f"{{key}} must be a {cls.__name__}, got {type(value).__name__}", key=key)


@dataclass(frozen=True, slots=True)
class LoopConfig:
    """One loop: valve + plant (+ internal controller), the unit it answers as, and where it came from."""

    name: str
    _: KW_ONLY
    description: str = ""
    valve: ValveConfig = ValveConfig()
    plant: PlantConfig  # required (keyword-only fields may follow defaulted ones)
    controller: ControllerConfig | None = None  # None: open loop / OP written by an external controller
    simulation: SimulationConfig = SimulationConfig()
    device: DeviceConfig = DeviceConfig()
    source: str = ""                            # file the loop was read from ("<mapping>" for dicts)

    def __post_init__(self) -> None:
        text(self.name, "name")
        if not self.name:
            raise ConfigError("{key} must not be empty", key="name")
        text(self.description, "description")
        text(self.source, "source")
        for key, cls in (("plant", PlantConfig), ("valve", ValveConfig), ("simulation", SimulationConfig),
                         ("device", DeviceConfig)):
            _instance(getattr(self, key), key, cls)
        _instance(self.controller, "controller", ControllerConfig, none_ok=True)
        if self.device.unit is None:
            raise ConfigError("{key} must be set for a loop", key="device.unit")


@dataclass(frozen=True, slots=True)
class ServerConfig:
    """A Modbus server: server-wide device settings and one or more loops on distinct addresses.

    A loop's address is ``(device.unit, device.block)``. The blocks of one unit must be ``0 .. B−1``
    without gaps (a fleet with ``loops_per_unit`` > 1 fills them in order).
    """

    device: DeviceConfig            # server-wide keys; its unit is None (units are per loop)
    loops: tuple[LoopConfig, ...]   # non-empty, (unit, block) addresses unique
    _: KW_ONLY
    source: str = ""
    opcua: OpcUaConfig = OpcUaConfig()   # the OPC UA server (port None: none)
    tls: TlsConfig = TlsConfig()         # the Modbus/TCP Security listener (port None: none)

    def __post_init__(self) -> None:
        _instance(self.device, "device", DeviceConfig)
        _instance(self.opcua, "opcua", OpcUaConfig)
        _instance(self.tls, "tls", TlsConfig)
        loops = sequence(self.loops, "loops", min_len=1)
        seen: dict[tuple[int, int], int] = {}
        blocks: dict[int, int] = {}
        for i, loop in enumerate(loops):
            _instance(loop, f"loops[{i}]", LoopConfig)
            address = (loop.device.unit, loop.device.block)
            if address in seen:
                j = seen[address]
                where = f"{address[0]}" + (f" block {address[1]}" if address[1] else "")
                raise ConfigError(f"{{key}} {where} is already used by loops[{j}] ({loops[j].name!r})",
                                  key=f"loops[{i}].unit")
            seen[address] = i
            blocks[address[0]] = max(blocks.get(address[0], 0), address[1] + 1)
            if address[1] and self.device.register_map is not None:
                raise ConfigError("{key}: a configured device.register_map places tags at any address of a unit, "
                                  "so each unit carries one loop (no fleet.loops_per_unit > 1)", key="loops")
        for unit, count in blocks.items():
            missing = next((b for b in range(count) if (unit, b) not in seen), None)
            if missing is not None:
                raise ConfigError(f"{{key}}: unit {unit} has block {count - 1} but no block {missing}; the blocks "
                                  f"of a unit must be 0..B-1 without gaps", key="loops")
        _set(self, loops=loops)
        text(self.source, "source")
