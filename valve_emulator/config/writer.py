"""Write a loop config back as YAML: the text :func:`~valve_emulator.config.load_loop` reads to an equal config.

Every key is written, defaults included, so a reader sees the whole loop without the schema at hand (the
full single-loop example of ``docs/config.md`` has the same layout). Numbers are written by PyYAML's
representer, which uses ``repr`` (the shortest text that reads back to the same float) and always puts a
dot in a float, so ``1e3`` can never come back as text. A header (the provenance of the numbers, say) goes
first as ``#`` comment lines.

The round trip ``load_loop(write) == config`` holds for every field but ``source`` (where the loop was read
from) and ``device.block`` (set by a fleet, not a YAML key).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import yaml

from valve_emulator.config.schema import KEYS, DisturbanceConfig, LoopConfig

__all__ = ["loop_to_mapping", "dump_loop", "write_loop"]


def _valve(cfg: LoopConfig) -> dict:
    v = cfg.valve
    out: dict = {"model": v.model}
    if v.seed_form is not None:   # keep the form that was typed (the loader would refuse both forms)
        out["seed_s"], out["seed_j"] = v.seed_form
    else:
        out["S"], out["J"] = v.S, v.J
    out.update(rest_time=v.rest_time, initial_direction=v.initial_direction, op0=v.op0, mv0=v.mv0,
               stuck0=v.stuck0, actuator_lag=v.actuator_lag, characteristic=v.characteristic,
               rangeability=v.rangeability, flow_limits=list(v.flow_limits),
               ma_table=[list(row) for row in v.ma_table], op_range=list(v.op_range))
    return out


def _disturbance(d: DisturbanceConfig) -> dict:
    keys = KEYS[f"plant.disturbance[{d.type}]"]
    return {k: getattr(d, k) for k in keys}


def _plant(cfg: LoopConfig) -> dict:
    p = cfg.plant
    out = {"num": list(p.num), "den": list(p.den), "delay": p.delay, "pv0": p.pv0, "u0": p.u0,
           "rest_flow": p.rest_flow, "pv_range": list(p.pv_range), "units": p.units,
           "disturbance": _disturbance(p.disturbance), "noise": p.noise}
    if p.alarms is not None:
        out["alarms"] = list(p.alarms)
    return out


def _controller(cfg: LoopConfig) -> dict | None:
    c = cfg.controller
    if c is None:
        return None
    return {"kc": c.kc, "ti": c.ti, "td": c.td, "sp": c.sp, "sp_steps": [list(s) for s in c.sp_steps],
            "bias": c.bias, "action": c.action, "op_limits": list(c.op_limits), "mode": c.mode}


def _device(cfg: LoopConfig) -> dict:
    d = cfg.device
    out = {k: getattr(d, k) for k in KEYS["device"]}
    out["word_order"] = str(d.word_order)
    out["instructor_hosts"] = list(d.instructor_hosts)
    out["roles"] = {name: list(tags) for name, tags in d.roles}
    return out


def loop_to_mapping(cfg: LoopConfig) -> dict:
    """The loop as a mapping in the YAML schema (plain Python data, sections in the documented order)."""
    s = cfg.simulation
    return {"name": cfg.name, "description": cfg.description, "valve": _valve(cfg), "plant": _plant(cfg),
            "controller": _controller(cfg), "simulation": {"dt": s.dt, "duration": s.duration, "seed": s.seed},
            "device": _device(cfg)}


class _Dumper(yaml.SafeDumper):
    """Block style for sections, flow style (``[1.0, 2.0]``) for lists of numbers and small mappings."""


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


_Dumper.add_representer(list, _represent_list)


def dump_loop(cfg: LoopConfig, *, header: str | Sequence[str] = ()) -> str:
    """The YAML text of ``cfg``, after ``header`` (lines, or one text) written as ``#`` comments."""
    lines = header.splitlines() if isinstance(header, str) else [str(line) for line in header]
    head = "".join(f"# {line}".rstrip() + "\n" for line in lines)
    body = yaml.dump(loop_to_mapping(cfg), Dumper=_Dumper, sort_keys=False, allow_unicode=True, width=120)
    return head + body


def write_loop(cfg: LoopConfig, path: str | os.PathLike, *, header: str | Sequence[str] = ()) -> None:
    """Write :func:`dump_loop` to ``path`` (UTF-8)."""
    Path(path).write_text(dump_loop(cfg, header=header), encoding="utf-8")
