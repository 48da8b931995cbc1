"""Read YAML configuration files (or in-memory mappings) into validated, frozen config objects.

The file is parsed exactly once, with PyYAML's safe loader: the node tree is composed (that is where line
numbers live), indexed by dotted key -> line, then constructed into plain Python data — the two halves of
``yaml.safe_load``. The data is then walked section by section: unknown keys, wrong types and bad values
raise :class:`~valve_emulator.config.schema.ConfigError` naming the file, the line (when the key came from
a file) and the dotted key, e.g. ``configs/x.yaml:7: plant.delay must be >= 0, got -3``. Nothing is
cached or mutated, so a failed load leaves every earlier result (and the caller's mapping) untouched.

Single-loop files have the sections ``valve, plant, controller, simulation, device`` (plus ``name`` and
``description``); multi-loop (server) files have ``device`` (server-wide, no ``unit``), ``loops`` and/or
``fleet``. The keys are listed in :data:`~valve_emulator.config.schema.KEYS` and documented in
``docs/config.md``.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import random
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NoReturn

import yaml

from valve_emulator.config.register_map import parse_register_map
from valve_emulator.config.schema import (
    DISTURBANCES,
    KEYS,
    MAX_BLOCKS,
    MAX_UNIT,
    ConfigError,
    ControllerConfig,
    DeviceConfig,
    DisturbanceConfig,
    LoopConfig,
    OpcUaConfig,
    PlantConfig,
    ServerConfig,
    SimulationConfig,
    TlsConfig,
    ValveConfig,
    choice,
    derive,
    integer,
    real,
    sequence,
)
from valve_emulator.physics.plant import check_transfer_function, fopdt, integrator
from valve_emulator.physics.stiction import seed_to_2005

__all__ = ["load_loop", "load_server", "loop_from_mapping", "server_from_mapping"]

_MERGE_TAG = "tag:yaml.org,2002:merge"
_REQUIRED_DISTURBANCE = {"step": ("amplitude",), "sine": ("amplitude", "period"), "random_walk": ("std",)}


def _join(prefix: str, key: str) -> str:
    if not prefix or not key:
        return prefix or key
    return prefix + key if key.startswith("[") else f"{prefix}.{key}"


def _parent(key: str) -> str:
    cut = max(key.rfind("."), key.rfind("["))
    return key[:max(cut, 0)]


class _Context:
    """Where the data came from (file name, key -> line) and how to report against it."""

    def __init__(self, source: str, lines: dict[str, int] | None = None):
        self.source, self.lines = source, lines or {}

    def line(self, key: str) -> int | None:
        while key:  # the nearest key that came from the file, e.g. a list's line for one of its items
            if key in self.lines:
                return self.lines[key]
            key = _parent(key)
        return None

    def locate(self, err: ConfigError, prefix: str = "") -> ConfigError:
        key = _join(prefix, err.key)
        return ConfigError(err.detail, key=key, source=self.source, line=self.line(key))

    def fail(self, key: str, detail: str) -> NoReturn:
        raise ConfigError(detail, key=key, source=self.source, line=self.line(key))

    def call(self, prefix: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` with any ConfigError re-keyed under `prefix` and located."""
        try:
            return fn(*args, **kwargs)
        except ConfigError as err:
            raise self.locate(err, prefix) from None

    def section(self, value: Any, key: str, allowed: tuple[str, ...], *, none_ok: bool = True) -> dict:
        """A copy of the mapping at `key` after checking every key is allowed (``null`` = empty)."""
        if value is None and none_ok:
            return {}
        if not isinstance(value, Mapping):
            got = "null" if value is None else type(value).__name__
            self.fail(key, f"{{key}} must be a mapping, got {got}")
        for k in value:
            if not isinstance(k, str) or k not in allowed:
                self.fail(_join(key, str(k)), f"unknown key {{key}} (allowed: {', '.join(allowed)})")
        return dict(value)

    def require(self, m: Mapping, key: str, *names: str) -> None:
        for name in names:
            if name not in m:
                self.fail(_join(key, name), "missing key {key}")


# --- reading a file ---------------------------------------------------------------------------------

def _index(node: yaml.Node | None, key: str, ctx: _Context, active: set[int]) -> None:
    """Record the line of every key and list item; reject duplicate keys (PyYAML keeps the last)."""
    if node is None or id(node) in active:  # an alias may refer back to its own ancestor
        return
    active.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen: dict[str, int] = {}
        for k, v in node.value:
            if k.tag == _MERGE_TAG or not isinstance(k, yaml.ScalarNode):
                continue
            child, line = _join(key, k.value), k.start_mark.line + 1
            if k.value in seen:
                raise ConfigError(f"duplicate key {{key}} (first given on line {seen[k.value]})",
                                  key=child, source=ctx.source, line=line)
            seen[k.value] = ctx.lines[child] = line
            _index(v, child, ctx, active)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            ctx.lines[f"{key}[{i}]"] = item.start_mark.line + 1
            _index(item, f"{key}[{i}]", ctx, active)
    active.discard(id(node))


def _read(path: str | os.PathLike[str]) -> tuple[Any, _Context]:
    ctx = _Context(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text (byte {exc.start})", source=ctx.source) from None
    except OSError as exc:
        raise ConfigError(f"cannot read the file: {exc.strerror or exc}", source=ctx.source) from None
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        _index(node, "", ctx, set())  # before construction, which rewrites merge keys in place
        data = None if node is None else loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = "; ".join(str(p) for p in (exc.context, exc.problem) if p)
        raise ConfigError(f"YAML syntax error: {what}", source=ctx.source,
                          line=mark.line + 1 if mark else None) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"YAML error: {exc}", source=ctx.source) from None
    except RecursionError:
        raise ConfigError("YAML nested too deeply", source=ctx.source) from None
    finally:
        loader.dispose()
    return data, ctx


# --- sections -----------------------------------------------------------------------------------------

def _valve(ctx: _Context, value: Any, key: str) -> ValveConfig:
    m = ctx.section(value, key, KEYS["valve"])
    given = [k for k in ("S", "J") if k in m]
    seed = [k for k in ("seed_s", "seed_j") if k in m]
    if given and seed:
        ctx.fail(_join(key, seed[0]), f"{{key}} cannot be combined with {_join(key, given[0])}: give S/J "
                 "(2005 convention) or seed_s/seed_j (seed paper), not both")
    if seed:
        s = ctx.call("", real, m.pop("seed_s", 0.0), _join(key, "seed_s"), ge=0)
        j = ctx.call("", real, m.pop("seed_j", 0.0), _join(key, "seed_j"), ge=0)
        m["S"], m["J"] = seed_to_2005(s, j)
        m["seed_form"] = (s, j)
    return ctx.call(key, ValveConfig, **m)


def _transfer_function(ctx: _Context, m: dict, key: str) -> tuple[Any, Any, Any]:
    """``(num, den, delay)`` from exactly one of the forms num/den/delay, fopdt, integrator."""
    forms = [f for f in ("num", "fopdt", "integrator") if f in m or (f == "num" and "den" in m)]
    if not forms:
        ctx.fail(key, "{key} must give the process as num + den (+ delay), fopdt or integrator")
    if len(forms) > 1:
        ctx.fail(_join(key, forms[1]), f"{{key}} cannot be combined with {_join(key, forms[0])}: "
                 "give exactly one plant form")
    form = forms[0]
    if form == "num":
        ctx.require(m, key, "num", "den")
        return m["num"], m["den"], m.get("delay", 0.0)
    if "delay" in m:
        ctx.fail(_join(key, "delay"), f"{{key}} is only for num/den; give {key}.{form}.delay instead")
    sub = _join(key, form)
    f = ctx.section(m[form], sub, KEYS[f"plant.{form}"], none_ok=False)
    ctx.require(f, sub, "gain", *(("tau",) if form == "fopdt" else ()))
    gain = ctx.call("", real, f["gain"], _join(sub, "gain"))
    if gain == 0:
        ctx.fail(_join(sub, "gain"), "{key} must be nonzero, got 0")
    delay = ctx.call("", real, f.get("delay", 0.0), _join(sub, "delay"), ge=0)
    if form == "integrator":
        return integrator(gain, delay)
    return fopdt(gain, ctx.call("", real, f["tau"], _join(sub, "tau"), ge=0), delay)


def _disturbance(ctx: _Context, value: Any, key: str) -> DisturbanceConfig:
    if value is None:
        return DisturbanceConfig()
    if not isinstance(value, Mapping):
        ctx.fail(key, "{key} must be a mapping such as {type: step, amplitude: 5.0, time: 100.0}")
    ctx.require(value, key, "type")
    kind = ctx.call("", choice, value["type"], _join(key, "type"), DISTURBANCES)
    m = ctx.section(value, key, KEYS[f"plant.disturbance[{kind}]"])
    ctx.require(m, key, *_REQUIRED_DISTURBANCE.get(kind, ()))
    return ctx.call(key, DisturbanceConfig, **m)


def _plant(ctx: _Context, value: Any, key: str) -> PlantConfig:
    m = ctx.section(value, key, KEYS["plant"], none_ok=False)
    num, den, delay = _transfer_function(ctx, m, key)
    for k in ("num", "den", "delay", "fopdt", "integrator"):
        m.pop(k, None)
    m["disturbance"] = _disturbance(ctx, m.get("disturbance"), _join(key, "disturbance"))
    return ctx.call(key, PlantConfig, num, den, delay=delay, **m)


def _device_section(ctx: _Context, value: Any, allowed: tuple[str, ...]) -> dict:
    """The ``device`` mapping, its ``register_map`` read with the file's lines (config/register_map.py)."""
    m = ctx.section(value, "device", allowed)
    if m.get("register_map") is not None:
        m["register_map"] = parse_register_map(m["register_map"], "device.register_map", source=ctx.source,
                                               line_of=ctx.line)
    return m


def _check_discretisation(ctx: _Context, plant: PlantConfig, dt: float, key: str) -> None:
    """Let the physics layer confirm it can discretise the plant at this dt (e.g. delay/dt not absurd)."""
    try:
        check_transfer_function(plant.num, plant.den, plant.delay, dt)
    except ValueError as exc:
        word = str(exc).split(" ", 1)[0]
        ctx.fail(_join(key, word) if word in ("num", "den", "delay") else key,
                 f"{{key}} is rejected by the plant model: {exc}")


def _loop(ctx: _Context, m: dict, key: str, *, device: DeviceConfig, default_name: str) -> LoopConfig:
    """A loop from an already key-checked mapping with sections valve, plant, controller, simulation."""
    ctx.require(m, key, "plant")
    valve = _valve(ctx, m.get("valve"), _join(key, "valve"))
    plant = _plant(ctx, m["plant"], _join(key, "plant"))
    sim_key = _join(key, "simulation")
    simulation = ctx.call(sim_key, SimulationConfig, **ctx.section(m.get("simulation"), sim_key,
                                                                    KEYS["simulation"]))
    _check_discretisation(ctx, plant, simulation.dt, _join(key, "plant"))
    controller = None
    if m.get("controller") is not None:
        c_key = _join(key, "controller")
        c = ctx.section(m["controller"], c_key, KEYS["controller"])
        ctx.require(c, c_key, "kc")
        c.setdefault("sp", plant.pv0)  # start at the operating point unless told otherwise
        controller = ctx.call(c_key, ControllerConfig, c.pop("kc"), **c)
    return ctx.call(key, LoopConfig, m.get("name", default_name), plant=plant,
                    description=m.get("description", ""), valve=valve, controller=controller,
                    simulation=simulation, device=device, source=ctx.source)


def _single(ctx: _Context, data: Any, default_name: str) -> LoopConfig:
    if data is None:
        ctx.fail("", "the file is empty; expected a mapping with at least a plant section")
    if isinstance(data, Mapping):
        for k in KEYS["server"][1:]:
            if k in data:
                ctx.fail(k, "{key} makes this a multi-loop (server) file; load it with load_server")
    top = ctx.section(data, "", KEYS[""], none_ok=False)
    device = ctx.call("device", DeviceConfig, **_device_section(ctx, top.get("device"), KEYS["device"]))
    return _loop(ctx, top, "", device=device, default_name=default_name)


def _vary(ctx: _Context, value: Any) -> dict[str, tuple[float, float]]:
    ranges = {}
    for k, v in ctx.section(value, "fleet.vary", KEYS["fleet.vary"]).items():
        key = f"fleet.vary.{k}"
        lo, hi = (ctx.call("", real, x, f"{key}[{i}]", **({"gt": 0} if k == "gain" else {"ge": 0}))
                  for i, x in enumerate(ctx.call("", sequence, v, key, length=2)))
        if lo > hi:
            ctx.fail(key, f"{{key}} must be [lo, hi] with lo <= hi, got [{lo:g}, {hi:g}]")
        ranges[k] = (lo, hi)
    return ranges


def _fleet(ctx: _Context, value: Any, device: DeviceConfig, used: set[int]) -> list[LoopConfig]:
    """Expand ``fleet`` into concrete loops on the lowest free units from ``first_unit``.

    With ``loops_per_unit = L`` each of those units carries ``L`` loops in blocks ``0..L-1`` (the last one
    possibly fewer): loop k sits on the (k // L)-th free unit, block k % L, so a fleet of N loops needs
    ``ceil(N / L)`` units and one port holds up to 247 × 2048 loops.

    Each varied quantity has its own random stream, ``random.Random("valve_emulator.fleet/<seed>/<key>")``
    (string seeds are hashed with SHA-512, so the stream is the same in every process), and loop k takes
    the k-th draw of ``uniform(lo, hi)``: adding a ``vary`` entry does not change the others' values, and
    neither does ``loops_per_unit`` (only where each loop answers).
    """
    m = ctx.section(value, "fleet", KEYS["fleet"], none_ok=False)
    ctx.require(m, "fleet", "count", "base")
    count = ctx.call("", integer, m["count"], "fleet.count", ge=1)
    first = ctx.call("", integer, m.get("first_unit", 1), "fleet.first_unit", ge=1, le=MAX_UNIT)
    per_unit = ctx.call("", integer, m.get("loops_per_unit", 1), "fleet.loops_per_unit", ge=1, le=MAX_BLOCKS)
    seed = ctx.call("", integer, m.get("seed", 0), "fleet.seed", ge=0)
    free = [u for u in range(first, MAX_UNIT + 1) if u not in used]
    if count > len(free) * per_unit:
        times = f" × loops_per_unit {per_unit}" if per_unit > 1 else ""
        hint = "" if per_unit > 1 else " (more loops: put several behind each unit with fleet.loops_per_unit)"
        ctx.fail("fleet.count", f"{{key}} must be <= {len(free) * per_unit} (units {first}..{MAX_UNIT} not used "
                 f"by loops{times}), got {count}{hint}")
    base_m = ctx.section(m["base"], "fleet.base", KEYS["fleet.base"], none_ok=False)
    base = _loop(ctx, base_m, "fleet.base", device=dataclasses.replace(device, unit=free[0]),
                 default_name="fleet")
    ranges = _vary(ctx, m.get("vary"))
    if "delay" in ranges:  # the longest delay must still be discretisable
        worst = dataclasses.replace(base.plant, delay=ranges["delay"][1])
        _check_discretisation(ctx, worst, base.simulation.dt, "fleet.vary")
    streams = {k: random.Random(f"valve_emulator.fleet/{seed}/{k}") for k in ranges}
    last = count - 1
    # Every draw lies in the box of the ranges, and every check a loop's values must pass is a bound on one
    # value (S, J, delay >= 0, finite coefficients) or a type, so a loop built at each corner of the box
    # with every check (dataclasses.replace) proves them all; the loops themselves are derived unchecked.
    for corner in itertools.product(*([(k, lo), (k, hi)] for k, (lo, hi) in ranges.items())):
        _fleet_loop(dataclasses.replace, base, device, dict(corner), free[last // per_unit],
                    min(per_unit, count) - 1, per_unit)
    order = [(q, *ranges[q], streams[q].random) for q in KEYS["fleet.vary"] if q in ranges]
    loops = []
    for k in range(count):
        # random.uniform(lo, hi) is lo + (hi - lo) * random(), spelled out: the same draws, a call less each
        draw = {q: lo + (hi - lo) * rnd() for q, lo, hi, rnd in order}
        loops.append(_fleet_loop(derive, base, device, draw, free[k // per_unit], k % per_unit, per_unit))
    return loops


def _fleet_loop(build, base: LoopConfig, device: DeviceConfig, draw: dict[str, float], unit: int, block: int,
                per_unit: int) -> LoopConfig:
    """Fleet loop with the varied quantities ``draw`` at ``(unit, block)``; ``build`` is ``dataclasses.replace``
    (checked) or :func:`~valve_emulator.config.schema.derive` (not checked again)."""
    valve, plant = base.valve, base.plant
    if "S" in draw or "J" in draw:  # the typed 2003-paper form no longer describes this valve
        valve = build(valve, S=draw.get("S", valve.S), J=draw.get("J", valve.J), seed_form=None)
    if "gain" in draw or "delay" in draw:
        gain = draw.get("gain", 1.0)
        plant = build(plant, num=tuple([c * gain for c in plant.num]), delay=draw.get("delay", plant.delay))
    name = f"{base.name}_{unit:03d}" + (f"_{block:04d}" if per_unit > 1 else "")
    return build(base, name=name, valve=valve, plant=plant, device=build(device, unit=unit, block=block))


def _server(ctx: _Context, data: Any, default_name: str) -> ServerConfig:
    if isinstance(data, Mapping) and not any(k in data for k in ("loops", "fleet")):
        loop = _single(ctx, data, default_name)
        return ServerConfig(dataclasses.replace(loop.device, unit=None), (loop,), source=ctx.source)
    top = ctx.section(data, "", KEYS["server"], none_ok=False)
    dev = _device_section(ctx, top.get("device"), KEYS["device"])
    if "unit" in dev:
        ctx.fail("device.unit", "{key} is not allowed in a multi-loop file; give each loops[i].unit")
    device = ctx.call("device", DeviceConfig, unit=None, **dev)
    loops = []
    if "loops" in top:
        for i, item in enumerate(ctx.call("", sequence, top["loops"], "loops", min_len=1)):
            key = f"loops[{i}]"
            m = ctx.section(item, key, KEYS["loops[i]"], none_ok=False)
            ctx.require(m, key, "unit")
            unit = ctx.call("", integer, m["unit"], f"{key}.unit", ge=1, le=MAX_UNIT)
            loops.append(_loop(ctx, m, key, device=dataclasses.replace(device, unit=unit),
                               default_name=f"loop_{unit:03d}"))
    if "fleet" in top:
        loops += _fleet(ctx, top["fleet"], device, {loop.device.unit for loop in loops})
    secure = {key: _secure_section(ctx, top.get(key), key, cls) for key, cls in (("opcua", OpcUaConfig),
                                                                                  ("tls", TlsConfig))}
    return ctx.call("", ServerConfig, device, tuple(loops), source=ctx.source, **secure)


def _secure_section(ctx: _Context, value: Any, key: str, cls: type) -> Any:
    """The ``opcua`` / ``tls`` section, its file paths made relative to the config file's folder."""
    m = ctx.section(value, key, KEYS[key])
    if not ctx.source.startswith("<"):
        base = Path(ctx.source).parent
        for k in ("certificate", "private_key", "users", "ca", "pki"):
            if isinstance(m.get(k), str):
                m[k] = str(base / m[k])
    return ctx.call(key, cls, **m)


# --- public entry points ------------------------------------------------------------------------------

def _default_name(source: str) -> str:
    return "loop" if source.startswith("<") else Path(source).stem


def load_loop(path: str | os.PathLike[str]) -> LoopConfig:
    """Load a single-loop YAML file; ``name`` defaults to the file stem. Raises ConfigError."""
    data, ctx = _read(path)
    return _single(ctx, data, _default_name(ctx.source))


def load_server(path: str | os.PathLike[str]) -> ServerConfig:
    """Load a multi-loop (server) file, or a single-loop file as a server of one loop on ``device.unit``."""
    data, ctx = _read(path)
    return _server(ctx, data, _default_name(ctx.source))


def loop_from_mapping(data: Mapping[str, Any], *, source: str = "<mapping>") -> LoopConfig:
    """Validate an in-memory single-loop mapping exactly as :func:`load_loop` does (no line numbers)."""
    return _single(_Context(source), data, _default_name(source))


def server_from_mapping(data: Mapping[str, Any], *, source: str = "<mapping>") -> ServerConfig:
    """Validate an in-memory multi-loop (or single-loop) mapping exactly as :func:`load_server` does."""
    return _server(_Context(source), data, _default_name(source))
