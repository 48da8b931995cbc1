"""The instructor station's model: one object over a running :class:`~valve_emulator.device.tick.Device`.

Everything the HTTP API and the pages can do is a method here, transport-free (the aiohttp adapter is
:mod:`valve_emulator.station.app`): the state of the loops as JSON, run/freeze and speed, snapshots and the
backtrack ring, malfunctions, the trainee's operator actions, alarms with acknowledge, the scenario and the
evaluation. A refused request raises :class:`StationError` carrying the HTTP status and the offending field;
nothing has changed then.

Operator actions (mode, SP in auto, OP in manual) are Modbus writes in all but transport: the station turns
the value into the register word a client would write (:func:`~valve_emulator.device.malfunctions.register_word`)
and hands it to :meth:`Device.write <valve_emulator.device.tick.Device.write>`, so the register map's checks
and error text apply unchanged (``register op_pct (holding 0) is writable only while the controller is in
manual``). A page can do nothing a Modbus client could not.

Alarms: a PV high and low limit per loop -- ``plant.alarms`` of its config (by default 10 % and 90 % of the
loop's PV range), or the scenario's
``limits`` -- raise an alarm that stays until acknowledged *and* back inside the limits (ISA-18.2's latched
alarm states, simplified: unacknowledged active, acknowledged active, unacknowledged returned). The device
computes them (:attr:`Device.alarms <valve_emulator.device.alarms.PvAlarms>`), so the station, the ``alarms``
register and OPC UA's alarm conditions show one state; the station adds the trainee's acknowledgements to the
evaluation.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from valve_emulator.device.malfunctions import Malfunction, MalfunctionError, parse_malfunction, register_word
from valve_emulator.device.registers import RegisterError, address_of
from valve_emulator.device.roles import OPERATOR, Role
from valve_emulator.device.snapshots import BacktrackRing, SnapshotError, SnapshotNotFound, SnapshotStore, check_name
from valve_emulator.errors import UserError
from valve_emulator.station.evaluation import Action, Evaluation, trend_png

__all__ = ["Station", "StationError"]

_log = logging.getLogger("valve_emulator.station")


class StationError(UserError):
    """A refused request: ``status`` (HTTP), ``field`` (the offending input) and the message."""

    def __init__(self, message: str, *, field: str, status: int = 400) -> None:
        super().__init__(message)
        self.field, self.status = field, status


def _number(body: Mapping[str, Any], key: str, *, lo: float = -math.inf, hi: float = math.inf) -> float:
    if key not in body:
        raise StationError(f"field {key!r} is required", field=key)
    value = body[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise StationError(f"field {key!r} must be a finite number, got {value!r}", field=key)
    if not lo <= value <= hi:
        raise StationError(f"field {key!r} must be in {lo:g}..{hi:g}, got {value!r}", field=key)
    return float(value)


def _checked_name(name: Any) -> str:
    """``name`` if it is a valid snapshot name; a path trick (``../x``, ``/etc``, a NUL) is a 400 naming it."""
    try:
        return check_name(name)
    except SnapshotError as exc:
        raise StationError(str(exc), field=exc.field) from None


class Station:
    """The station over ``device`` (see the module docstring).

    ``snapshots``: where named snapshots live (a :class:`SnapshotStore`, with or without a directory);
    ``backtrack``: the automatic ring, or ``None``.
    """

    def __init__(self, device: Any, *, snapshots: SnapshotStore | None = None,
                 backtrack: BacktrackRing | None = None) -> None:
        self.device = device
        self.bank = device.bank
        self.snapshots = snapshots if snapshots is not None else SnapshotStore()
        self.backtrack = backtrack
        n = self.bank.n
        self.names = [lp.name for lp in self.bank.loops]
        self.pv_units = [lp.plant.units for lp in self.bank.loops]
        scaling = device.scaling
        lo, hi = np.asarray(scaling.pv_lo, dtype=float), np.asarray(scaling.pv_hi, dtype=float)
        self.pv_lo, self.pv_hi = lo, hi
        #: the device's PV alarms; their limit arrays are the station's (a scenario changes them in place)
        self.alarms = device.alarms
        self.lim_lo, self.lim_hi = self.alarms.lo, self.alarms.hi
        self.revealed: set[int] = set()   # unit ids whose MV the trainee sees
        self.evaluation = Evaluation(n=n, dt=self.bank.dt, lo=self.lim_lo, hi=self.lim_hi,
                                     units=list(device.units))
        self.notes: list[dict[str, Any]] = []   # instructor notes (scenario lines), newest last
        self.scenario: Any = None              # a ScenarioRun (valve_emulator.station.scenario_run)
        self._prev_mv = self.bank.mv
        self._moving = np.zeros(n, dtype=bool)
        device.on_tick.append(self._on_tick)

    # --- per tick -------------------------------------------------------------------------------------

    def _on_tick(self, device: Any) -> None:
        b = self.bank
        t, pv, sp, op = b.sample_time, b.pv, b._sp, b.op
        mv = b.mv
        self._moving = np.abs(mv - self._prev_mv) > 1e-9
        self._prev_mv = mv
        self.evaluation.add_sample(t, sp, pv, op, mv)
        if self.backtrack is not None and self.backtrack.due(t):
            self.backtrack.add(device.snapshot(f"bt-{t:08.1f}"))
        if self.scenario is not None:
            self.scenario.on_tick(self, t)

    # --- state ----------------------------------------------------------------------------------------

    def index_of(self, unit: Any) -> int:
        if isinstance(unit, str) and unit.isdigit():
            unit = int(unit)
        if isinstance(unit, bool) or not isinstance(unit, int):
            raise StationError(f"field 'unit' must be a unit id (a whole number), got {unit!r}"[:200], field="unit")
        if unit not in self.device.unit_index:
            raise StationError(f"field 'unit': no loop at unit {unit!r}", field="unit", status=404)
        return self.device.unit_index[unit]

    def loops_state(self, indices: list[int], *, instructor: bool) -> list[dict[str, Any]]:
        b = self.bank
        pv, sp, op, mv = b.pv[indices], b._sp[indices], b.op[indices], b.mv[indices]
        auto, ctl, stuck = b.auto[indices], b.has_controller[indices], b.stuck[indices]
        frozen, S, J = b.frozen[indices], b.S[indices], b.J[indices]
        out = []
        for k, i in enumerate(indices):
            unit = self.device.units[i]
            loop = {"unit": unit, "name": self.names[i], "pv": float(pv[k]), "sp": float(sp[k]),
                    "op": float(op[k]),
                    "mode": ("auto" if auto[k] else "manual") if ctl[k] else "external",
                    "pv_range": [float(self.pv_lo[i]), float(self.pv_hi[i])], "pv_units": self.pv_units[i],
                    "limits": [float(self.lim_lo[i]), float(self.lim_hi[i])], "alarm": str(self.alarms.state(i)),
                    "status": {"stuck": bool(stuck[k]), "moving": bool(self._moving[i]),
                               "saturated": bool(op[k] <= 0.0 or op[k] >= 100.0), "fault": bool(frozen[k])},
                    "mv_revealed": unit in self.revealed}
            if instructor or unit in self.revealed:
                loop["mv"] = float(mv[k])
            if instructor:
                loop.update(S=float(S[k]), J=float(J[k]), load=float(b.load[i]), noise=float(b.noise_std[i]),
                            sensor_bias=float(b.pv_bias[i]),
                            sensor_stuck=bool(np.isfinite(b.pv_stuck[i])))
            out.append(loop)
        return out

    def state(self, *, instructor: bool, units: list[int] | None = None) -> dict[str, Any]:
        """``time``, ``running``, ``time_scale``, ``tick``, ``loops`` (all, or those of ``units``)."""
        d = self.device
        indices = list(range(self.bank.n)) if units is None else [self.index_of(u) for u in units]
        state = {"time": float(self.bank.sample_time), "tick": d.ticks, "running": not d.frozen,
                 "time_scale": d.time_scale if math.isfinite(d.time_scale) else None, "n_loops": self.bank.n,
                 "loops": self.loops_state(indices, instructor=instructor)}
        if instructor:
            state["malfunctions"] = d.malfunctions.active if d.malfunctions is not None else []
            state["notes"] = self.notes[-20:]
            state["scenario"] = self.scenario.describe() if self.scenario is not None else None
            state["score"] = self.report(brief=True)["score"]
        else:
            state["hints"] = list(self.evaluation.hints_released)
        return state

    def loop_list(self) -> list[dict[str, Any]]:
        """Unit and name of every loop (the fleet's loop list)."""
        return [{"unit": u, "name": n} for u, n in zip(self.device.units, self.names)]

    # --- instructor: run/freeze, speed ----------------------------------------------------------------

    async def run(self) -> None:
        await self.device.resume()
        self._log_instructor("run")

    async def freeze(self) -> None:
        await self.device.freeze()
        self._log_instructor("freeze")

    async def speed(self, body: Mapping[str, Any]) -> None:
        x = _number(body, "time_scale", lo=0.01, hi=1000.0)
        await self.device.set_time_scale(x)
        self._log_instructor("speed", x)

    # --- snapshots --------------------------------------------------------------------------------------

    def save_snapshot(self, body: Mapping[str, Any]) -> dict[str, Any]:
        if "name" not in body:
            raise StationError("field 'name' is required", field="name")
        name = _checked_name(body["name"])
        try:
            snap = self.device.snapshot(name)
            self.snapshots.put(snap)
        except SnapshotError as exc:
            raise StationError(str(exc), field=exc.field) from None
        except OSError as exc:
            raise StationError(f"snapshot {body['name']!r} could not be written: {exc}", field="name",
                               status=500) from None
        self._log_instructor("snapshot", name)
        return snap.summary()

    def list_snapshots(self) -> dict[str, Any]:
        return {"snapshots": [s.summary() for s in self.snapshots],
                "broken": [{"name": name, "error": why} for name, why in sorted(self.snapshots.broken.items())],
                "backtrack": [s.summary() for s in self.backtrack] if self.backtrack is not None else []}

    def _find(self, name: str):
        _checked_name(name)
        try:
            return self.snapshots.get(name)
        except SnapshotNotFound:
            if self.backtrack is not None:
                try:
                    return self.backtrack.get(name)
                except SnapshotNotFound:
                    pass
            raise StationError(f"no snapshot named {name!r}", field="name", status=404) from None
        except SnapshotError as exc:   # its file is broken: the message names the file and what is wrong
            raise StationError(str(exc), field=exc.field, status=409) from None

    def restore_snapshot(self, name: str) -> dict[str, Any]:
        snap = self._find(name)
        try:
            self.device.restore(snap)
        except SnapshotError as exc:
            raise StationError(str(exc), field=exc.field, status=409) from None
        self._prev_mv = self.bank.mv
        if self.backtrack is not None:
            self.backtrack.reset(self.bank.sample_time)
        self._log_instructor("restore", name)
        return snap.summary()

    def delete_snapshot(self, name: str) -> None:
        _checked_name(name)
        try:
            self.snapshots.delete(name)
        except SnapshotNotFound:
            raise StationError(f"no snapshot named {name!r}", field="name", status=404) from None
        self._log_instructor("delete_snapshot", name)

    # --- malfunctions, reveal, hints --------------------------------------------------------------------

    def malfunction(self, body: Any) -> dict[str, Any]:
        """Check a malfunction request (``POST /api/malfunctions``) and :meth:`inject` it."""
        try:
            m = parse_malfunction(body, unit_index=self.device.unit_index, scaling=self.device.scaling)
        except MalfunctionError as exc:
            raise StationError(str(exc), field=exc.field) from None
        return self.inject(m)

    def inject(self, m: Malfunction) -> dict[str, Any]:
        """Apply a checked malfunction now and log it as the instructor's (the evaluation times the response)."""
        try:
            self.device.inject(m)
        except MalfunctionError as exc:
            raise StationError(str(exc), field=exc.field) from None
        t = float(self.bank.t)
        self.evaluation.malfunction(t, m.unit, m.kind.value)
        self._log_instructor("malfunction", m.as_dict(), unit=m.unit)
        return m.as_dict()

    def reveal(self, body: Mapping[str, Any]) -> None:
        index = self.index_of(body.get("unit"))
        show = body.get("mv", True)
        if not isinstance(show, bool):
            raise StationError(f"field 'mv' must be true or false, got {show!r}", field="mv")
        unit = self.device.units[index]
        (self.revealed.add if show else self.revealed.discard)(unit)
        self._log_instructor("reveal_mv" if show else "hide_mv", unit=unit)

    # --- trainee: operator actions, alarms ---------------------------------------------------------------

    def operate(self, unit: Any, body: Mapping[str, Any], *, who: str = "trainee",
                role: Role = OPERATOR) -> dict[str, Any]:
        """One operator action on ``unit``: ``{"mode": "auto"|"manual"}``, ``{"sp": x}`` or ``{"op": x}``, by a
        client of ``role`` (:mod:`~valve_emulator.device.roles`; a role that does not write the tag: 403)."""
        index = self.index_of(unit)
        keys = [k for k in ("mode", "sp", "op") if k in body]
        extra = [k for k in body if k not in ("mode", "sp", "op")]
        if extra:
            raise StationError(f"field {extra[0]!r}: an operator action is one of mode, sp, op", field=extra[0])
        if len(keys) != 1:
            raise StationError("request body: exactly one of fields 'mode', 'sp', 'op' is required", field="body")
        key = keys[0]
        value = body[key]
        if key not in role.tags:   # the keys are the tags: op, sp, mode
            raise StationError(f"field {key!r}: role {role.name!r} does not write {key}", field=key, status=403)
        if key == "mode":
            if value not in ("auto", "manual"):
                raise StationError(f"field 'mode' must be 'auto' or 'manual', got {value!r}", field="mode")
            name, word, action = "mode", 1 if value == "auto" else 0, value
        else:
            value = _number(body, key)
            name, action = ("sp", "sp") if key == "sp" else ("op_pct", "op")
        t = float(self.bank.sample_time)
        try:
            if key != "mode":   # a value no register word can carry is refused here, with the map's text
                word = register_word(name, value, self.device.scaling, index)
            self.device.write(index, address_of(name), [word], role=role)
        except RegisterError as exc:
            self.evaluation.action(Action(who=who, unit=self.device.units[index], action=action, value=value,
                                          sim_time=t, accepted=False, message=str(exc)))
            raise StationError(str(exc), field=key, status=409) from None
        self.evaluation.action(Action(who=who, unit=self.device.units[index], action=action, value=value,
                                      sim_time=t))
        return {"unit": self.device.units[index], key: value}

    def acknowledge(self, unit: Any, *, who: str = "trainee") -> dict[str, Any]:
        """Acknowledge ``unit``'s PV alarm (an active one stays active, a returned one becomes normal) and
        record the action; returns the alarm state after it."""
        index = self.index_of(unit)
        self.alarms.acknowledge(index)
        self.evaluation.action(Action(who=who, unit=self.device.units[index], action="ack",
                                      sim_time=float(self.bank.sample_time)))
        return {"unit": self.device.units[index], "alarm": str(self.alarms.state(index))}

    # --- report -----------------------------------------------------------------------------------------

    def report(self, *, brief: bool = False) -> dict[str, Any]:
        rules = self.scenario.scoring if self.scenario is not None else None
        expert = self.scenario.expert if self.scenario is not None else None
        report = self.evaluation.report(float(self.bank.sample_time), names=self.names, score_rules=rules,
                                        expert=expert)
        if brief:
            return {"score": report["score"]}
        return report

    def trend_png(self, unit: Any) -> bytes:
        index = self.index_of(unit)
        if index >= self.evaluation.trend.loops:
            raise StationError(f"field 'unit': the trend keeps only the first {self.evaluation.trend.loops} loops",
                               field="unit", status=404)
        return trend_png(self.evaluation.trend.series(index), title=f"unit {self.device.units[index]} "
                         f"({self.names[index]})", show_mv=True)

    def reset_session(self) -> None:
        self.evaluation.reset(float(self.bank.sample_time))
        self._log_instructor("session_start")

    def _log_instructor(self, action: str, value: Any = None, *, unit: int | None = None) -> None:
        self.evaluation.action(Action(who="instructor", unit=unit, action=action, value=value,
                                      sim_time=float(self.bank.sample_time), wall_time=time.time()))
