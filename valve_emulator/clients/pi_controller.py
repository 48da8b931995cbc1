"""``valve-emulator plc`` (or ``python -m valve_emulator.clients.pi_controller``): a soft PLC -- PI(D) over
Modbus TCP at a fixed scan time.

Every scan it reads PV (and the set point, when ``--sp-register`` names one), runs one step of
:class:`valve_emulator.physics.controller.PID` (position form, anti-windup, derivative on PV) and writes
OP. Defaults fit the emulator's map: PV from ``pv_f32`` (float32, engineering units), OP to ``op_pct``
(% × 100). Any other device works through the address flags, e.g. PV from an input register and OP as a
4-20 mA current in µA::

    python -m valve_emulator.clients.pi_controller --port 502 --pv input:24:float32 --op holding:1:uint16:160:4000 \\
        --word-order CDAB --kc 0.2 --ti 10 --sp 1.0

Settings come from flags, or from a YAML file (``--config``) whose keys are the long flag names with
``_`` for ``-`` (``host, port, unit, timeout, word_order, scan, time_scale, kc, ti, td, action, bias,
op_limits, sp, sp_register, pv, op, device_time, duration``); a flag on the command line wins over the file.

Time: the controller's sample time is ``dt = scan × time_scale``: ``--scan`` is the wall-clock period
of the PLC and ``--time-scale`` tells it how many process seconds pass per wall second (1 for a real
plant; 10 for ``valve-emulator serve --time-scale 10``). Scans are due at absolute deadlines, so their
mean period is exact; a scan more than one period late skips the missed ones (counted as overruns).
A device that publishes its own clock can pace the PLC instead (``--device-time time`` for the
emulator): the PLC then scans on the device's time grid, exactly every ``dt`` device seconds (see
:mod:`valve_emulator.clients._schedule`), so an emulator that runs faster than real time, or falls behind under load,
sees exactly the controller a real plant would.

Start and stop are bumpless: the controller starts from the OP it reads back from the device (the
``--op`` register) and, without ``--sp``, holds the PV it finds as set point. Ctrl-C (SIGINT) or SIGTERM
stops it after the current scan without writing anything more: OP stays where it was.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TextIO

import yaml

from valve_emulator.clients._modbus import (
    ABCD,
    CDAB,
    ConnectionSettings,
    DeviceError,
    Point,
    Reader,
    add_connection_arguments,
    check_connection_arguments,
    parse_point,
)
from valve_emulator.clients._run import client_main
from valve_emulator.clients._schedule import next_or_retry, schedule_for
from valve_emulator.errors import UserError
from valve_emulator.physics.controller import PID

__all__ = [
    "ControllerSettings",
    "ControllerSummary",
    "add_arguments",
    "build_parser",
    "main",
    "run",
    "run_controller",
    "settings_from_args",
]

PROG = "python -m valve_emulator.clients.pi_controller"


@dataclass(frozen=True)
class ControllerSettings(ConnectionSettings):
    """A soft PLC's settings (see the module docstring for their meaning and units)."""

    scan: float = 0.1                 # s of wall time per scan
    time_scale: float = 1.0           # process seconds per wall second: dt = scan * time_scale
    kc: float = 0.2                   # % OP per PV unit, > 0
    ti: float | None = 10.0           # s; None (or 0 on the command line) = no integral action
    td: float = 0.0                   # s
    action: str = "reverse"           # reverse: OP falls when PV rises (positive process gain)
    bias: float = 50.0                # % OP at zero error
    op_limits: tuple[float, float] = (0.0, 100.0)
    sp: float | None = None           # fixed set point (PV units); None = read --sp-register or hold PV
    sp_register: str | None = None    # SPEC of a set point served by the device
    pv: str = "pv_f32"                # SPEC
    op: str = "op_pct"                # SPEC (a holding register)
    duration: float | None = None     # wall s, then stop as on Ctrl-C (None = run until stopped)
    device_time: str | None = None    # SPEC of the device's clock: scan on it instead of the wall clock

    def __post_init__(self) -> None:
        def bad(key: str, msg: str) -> ValueError:
            return ValueError(f"{key.replace('_', '-')} {msg}")

        for key in ("port", "unit", "scan", "time_scale", "kc", "ti", "td", "bias", "sp", "duration", "timeout"):
            v = getattr(self, key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise bad(key, f"must be a number, got {v!r}")
        for key in ("scan", "time_scale", "kc", "timeout"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise bad(key, f"must be a number > 0, got {v!r}")
        if self.ti is not None and not (math.isfinite(self.ti) and self.ti > 0):
            raise bad("ti", f"must be > 0 s (or 0/None for no integral action), got {self.ti!r}")
        if not (math.isfinite(self.td) and self.td >= 0):
            raise bad("td", f"must be >= 0 s, got {self.td!r}")
        if self.action not in ("reverse", "direct"):
            raise bad("action", f"must be reverse or direct, got {self.action!r}")
        if self.word_order not in (ABCD, CDAB):
            raise bad("word_order", f"must be ABCD or CDAB, got {self.word_order!r}")
        lim = self.op_limits
        if (not isinstance(lim, (tuple, list)) or len(lim) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in lim)):
            raise bad("op_limits", f"must be two numbers LO HI, got {lim!r}")
        lo, hi = lim
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise bad("op_limits", f"must be LO HI with LO < HI, got {self.op_limits!r}")
        for key in ("sp", "bias"):
            v = getattr(self, key)
            if v is not None and not math.isfinite(v):
                raise bad(key, f"must be finite, got {v!r}")
        if self.duration is not None and not self.duration > 0:
            raise bad("duration", f"must be > 0 s, got {self.duration!r}")
        if self.sp is not None and self.sp_register is not None:
            raise UserError("give either sp (a fixed set point) or sp-register, not both")
        for key in ("pv", "op", "sp_register", "device_time"):
            if getattr(self, key) is not None:
                parse_point(getattr(self, key), what=key.replace("_", "-"))
        if parse_point(self.op, what="op").table != "holding":
            raise bad("op", f"must be a holding register (it is written), got {self.op!r}")

    @property
    def dt(self) -> float:
        """The controller's sample time in process seconds."""
        return self.scan * self.time_scale


@dataclass
class ControllerSummary:
    scans: int = 0
    overruns: int = 0
    errors: int = 0
    sp: float = math.nan
    op: float = math.nan       # the last OP written


async def run_controller(settings: ControllerSettings, *, stop: asyncio.Event | None = None,
                         log: TextIO | None = None, clock: Callable[[], float] = time.monotonic,
                         prog: str = PROG) -> ControllerSummary:
    """Run the PLC until ``stop`` is set (or ``settings.duration`` has passed); OP is left as last written.

    ``log`` receives a line at the start, one at the first failure and one at the end, prefixed with ``prog``.

    The first read and the first write must succeed (``ConnectionError`` / :class:`DeviceError`); later
    failures are counted, reported once, and the scan is skipped (OP held).
    """
    s = settings
    pv_point, op_point = parse_point(s.pv, what="pv"), parse_point(s.op, what="op")
    points: dict[str, Point] = {"pv": pv_point}
    if s.sp_register is not None:
        points["sp"] = parse_point(s.sp_register, what="sp-register")
    if s.device_time is not None:
        points["t"] = parse_point(s.device_time, what="device-time")
    reader = Reader(points, word_order=s.word_order)
    link = s.link()
    summary = ControllerSummary()
    lo, hi = s.op_limits
    try:
        await link.connect()
        first = await reader.read(link)
        try:  # bumpless start from the OP the device holds now
            op0 = (await Reader({"op": op_point}, word_order=s.word_order).read(link))["op"]
        except DeviceError:
            op0 = s.bias   # a write-only output: start from the bias
        op0 = min(max(op0, lo), hi)
        sp = s.sp if s.sp is not None else first.get("sp", first["pv"])
        pid = PID(kc=s.kc, ti=s.ti, td=s.td, bias=s.bias, direct=s.action == "direct", op_min=lo, op_max=hi,
                  dt=s.dt)
        pid.reset(first["pv"], sp, op0)
        summary.sp = sp
        if log is not None:
            print(f"{prog}: unit {s.unit} at {s.host}:{s.port}; PV {first['pv']:g}, SP {sp:g}, OP {op0:g} %; "
                  f"scan {s.scan:g} s, dt {s.dt:g} s", file=log, flush=True)
        t0 = clock()
        schedule = schedule_for(s.dt if s.device_time is not None else None, s.scan, clock)
        if s.device_time is not None:
            schedule.seen(first["t"])

        async def read() -> dict[str, float]:
            return await reader.read(link)

        def failed(exc: Exception) -> None:   # counted; the first reported
            summary.errors += 1
            if log is not None and summary.errors == 1:
                print(f"{prog}: {exc}; holding OP and retrying", file=log, flush=True)

        sample: dict[str, float] | None = first
        while True:
            if sample is not None:
                if "sp" in sample:
                    sp = summary.sp = sample["sp"]
                op = pid(sp, sample["pv"])
                try:
                    await link.write(op_point.address, op_point.encode(op, s.word_order))
                    summary.op = op
                except (ConnectionError, DeviceError) as exc:
                    if summary.scans == 0:
                        raise
                    failed(exc)
                summary.scans += 1
            if (stop is not None and stop.is_set()) or (s.duration is not None and clock() - t0 >= s.duration):
                break
            sample = await next_or_retry(schedule, read, stop, retry=s.scan, failed=failed)
            summary.overruns = schedule.late + schedule.off_grid
    finally:
        link.close()   # nothing is written on the way out: OP stays where it was
    if log is not None:
        print(f"{prog}: stopped after {summary.scans} scans ({summary.overruns} overruns, {summary.errors} "
              f"errors); OP left at {summary.op:g} %", file=log, flush=True)
    return summary


DESCRIPTION = "Soft PLC: a PI(D) controller over Modbus TCP (reads PV, writes OP at a fixed scan time)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The soft PLC's flags (``python -m valve_emulator.clients.pi_controller`` and ``valve-emulator plc``)."""
    p.add_argument("--config", type=Path, metavar="PLC.yaml", help="settings file (keys = long flag names)")
    add_connection_arguments(p, defaults=False)   # unset flags fall back to the file, then the defaults
    g = p.add_argument_group("controller")
    g.add_argument("--scan", type=float, metavar="S", help="wall seconds per scan (default 0.1)")
    g.add_argument("--time-scale", type=float, metavar="X",
                   help="process seconds per wall second, dt = scan x X (default 1)")
    g.add_argument("--kc", type=float, help="gain, %% OP per PV unit (default 0.2)")
    g.add_argument("--ti", type=float, metavar="S", help="integral time, s; 0 = none (default 10)")
    g.add_argument("--td", type=float, metavar="S", help="derivative time, s (default 0)")
    g.add_argument("--action", choices=("reverse", "direct"), help="reverse: OP falls as PV rises (default)")
    g.add_argument("--bias", type=float, help="%% OP at zero error (default 50)")
    g.add_argument("--op-limits", type=float, nargs=2, metavar=("LO", "HI"), help="%% (default 0 100)")
    g.add_argument("--sp", type=float, help="fixed set point, PV units (default: hold the PV found at start)")
    g.add_argument("--sp-register", metavar="SPEC", help="read the set point from the device instead")
    g.add_argument("--pv", metavar="SPEC", help="PV register (default pv_f32)")
    g.add_argument("--op", metavar="SPEC", help="OP register, written (default op_pct)")
    g.add_argument("--device-time", metavar="SPEC",
                   help="scan on the device's clock read from this register (the emulator's: time): exactly "
                        "one scan per dt = scan x time-scale device seconds")
    g.add_argument("--duration", type=float, metavar="S", help="stop after S wall seconds (default: Ctrl-C)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION)
    add_arguments(p)
    return p


_KEYS = tuple(f.name for f in fields(ControllerSettings))


def _from_file(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise UserError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping of settings, got {type(data).__name__}")
    for key in data:
        if key not in _KEYS:
            raise UserError(f"{path}: unknown key {key!r} (allowed: {', '.join(_KEYS)})")
    if isinstance(data.get("op_limits"), list):
        data["op_limits"] = tuple(data["op_limits"])
    return data


def settings_from_args(args: argparse.Namespace) -> ControllerSettings:
    """Defaults < ``--config`` file < flags; ``UserError`` naming the setting (and the file)."""
    values: dict[str, Any] = _from_file(args.config) if args.config is not None else {}
    for key in _KEYS:
        flag = getattr(args, key, None)
        if flag is not None:
            values[key] = tuple(flag) if key == "op_limits" else flag
    if values.get("ti") == 0:
        values["ti"] = None
    try:
        settings = ControllerSettings(**values)
    except (TypeError, ValueError) as exc:
        where = f"{args.config}: " if args.config is not None else ""
        raise UserError(f"{where}{exc}") from None
    check_connection_arguments(argparse.Namespace(port=settings.port, unit=settings.unit, timeout=settings.timeout))
    return settings


def run(args: argparse.Namespace, *, prog: str = PROG) -> int:
    """Run the PLC as the flags say; messages start with ``prog``.

    Exit codes: 0 stopped cleanly (Ctrl-C, SIGTERM, --duration), 1 the device failed, 2 bad settings.
    """
    return client_main(prog, args, settings_from_args,
                       lambda settings, stop: run_controller(settings, stop=stop, log=sys.stderr, prog=prog))


def main(argv: list[str] | None = None) -> int:
    """``python -m valve_emulator.clients.pi_controller``; exit codes as :func:`run`."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
