"""``valve-emulator serve [CONFIG] [--host 127.0.0.1] [--port 5020] [--time-scale X]``: run the device.

SIGINT/SIGTERM stop it (a recording is complete up to the last tick: every row is flushed as written).
SIGHUP re-reads CONFIG and applies its connection and access settings (``device.read_only``,
``instructor_*``, ``max_connections``, ``idle_timeout``, ``frame_timeout``, ``error_rate``) at once; other
changes are reported as needing a restart, and an invalid file keeps the running config and logs why.
``--read-only`` and ``--max-connections`` win over the file, also after a reload.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import logging
import math
import signal
import sys
from pathlib import Path

NAME = "serve"
HELP = "serve the valve and process as a Modbus TCP device on a real-time tick"

_log = logging.getLogger("valve_emulator.serve")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="?", metavar="CONFIG",
                   help="server or loop config (default: the seed's concentration loop, sticky valve, external controller)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default %(default)s; 0.0.0.0 = all interfaces)")
    from valve_emulator.device.registers import DEFAULT_PORT

    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (default %(default)s; 0 picks a free port)")
    p.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                   help="simulated seconds per wall second (default %(default)s; same physics, faster clock)")
    p.add_argument("--uvloop", action="store_true", help="use uvloop's event loop (pip install uvloop)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.add_argument("--read-only", action="store_true",
                   help="refuse every write with exception 0x01 (illegal function), whatever CONFIG says")
    p.add_argument("--max-connections", type=int, metavar="N",
                   help="simultaneous client connections (default: device.max_connections, 64)")
    p.add_argument("--record", type=Path, metavar="FILE.csv",
                   help="record every loop once per tick (one flushed CSV line per tick); with several loops "
                        "each unit U goes to FILE_uUUU.csv")
    p.add_argument("--record-unit", type=int, action="append", metavar="U",
                   help="record only this unit (repeatable; one unit records to FILE.csv itself)")


def _check(args: argparse.Namespace) -> None:
    if not (0 <= args.port <= 65535):
        raise ValueError(f"--port must be 0..65535, got {args.port}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise ValueError(f"--time-scale must be a finite number > 0, got {args.time_scale}")
    if args.max_connections is not None and not 1 <= args.max_connections <= 65535:
        raise ValueError(f"--max-connections must be 1..65535, got {args.max_connections}")
    if args.record_unit and args.record is None:
        raise ValueError("--record-unit needs --record FILE.csv")


def apply_overrides(config, *, read_only: bool = False, max_connections: int | None = None):
    """``config`` with the command line's ``--read-only`` / ``--max-connections`` in every device section."""
    changes = {k: v for k, v in (("read_only", read_only or None), ("max_connections", max_connections))
               if v is not None}
    if not changes:
        return config
    loops = tuple(dataclasses.replace(lp, device=dataclasses.replace(lp.device, **changes)) for lp in config.loops)
    return dataclasses.replace(config, device=dataclasses.replace(config.device, **changes), loops=loops)


def reload_config(server, path: Path | None, *, read_only: bool = False,
                  max_connections: int | None = None) -> bool:
    """Re-read ``path`` and apply its live settings to ``server``; ``False`` (logged, nothing changed) if bad."""
    from valve_emulator.config import load_server

    if path is None:
        _log.warning("config reload: no config file (serving the embedded default device); nothing to reload")
        return False
    try:
        config = apply_overrides(load_server(path), read_only=read_only, max_connections=max_connections)
    except (ValueError, OSError) as exc:  # ConfigError is a ValueError and names file, line and key
        _log.error("config reload failed, keeping the running config: %s", exc)
        return False
    restart = server.reconfigure(config)
    later = f"; needs a restart to apply: {', '.join(restart)}" if restart else ""
    print(f"valve-emulator: reloaded {path}{later}", flush=True)
    return True


async def serve(config, *, host: str, port: int, time_scale: float, ready=None, config_path: Path | None = None,
                record: Path | None = None, record_units=None, read_only: bool = False,
                max_connections: int | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or cancellation); ``ready(server)`` is called once listening.

    SIGHUP reloads ``config_path`` (:func:`reload_config`); ``record`` records ``record_units`` (default
    all) with :class:`~valve_emulator.device.record.TickRecorder`.
    """
    from valve_emulator.device.guard import binds_all_interfaces
    from valve_emulator.device.record import TickRecorder
    from valve_emulator.device.server import EmulatorServer

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    handlers = {signal.SIGINT: stop.set, signal.SIGTERM: stop.set}
    for sig, handler in handlers.items():
        try:
            loop.add_signal_handler(sig, handler)
        except (NotImplementedError, RuntimeError):  # not the main thread / not supported
            pass
    try:
        async with EmulatorServer(config, host=host, port=port, time_scale=time_scale) as srv:
            hup = getattr(signal, "SIGHUP", None)
            if hup is not None:  # installed before the "listening" line, which tells a supervisor we are up
                handlers[hup] = lambda: reload_config(srv, config_path, read_only=read_only,
                                                      max_connections=max_connections)
                try:
                    loop.add_signal_handler(hup, handlers[hup])
                except (NotImplementedError, RuntimeError):
                    pass
            units = ", ".join(f"{u} ({lp.name})" for u, lp in zip(srv.units, config.loops))
            print(f"valve-emulator: listening on {host}:{srv.port}, unit ids {units}; tick {config.device.tick:g} s, "
                  f"time-scale {time_scale:g}; Ctrl-C stops", flush=True)
            if binds_all_interfaces(host):
                print("valve-emulator: WARNING: bound to all interfaces. Modbus TCP has no authentication: "
                      "anyone who can reach this port can move the valve. Use an isolated network.",
                      file=sys.stderr, flush=True)
            recorder = TickRecorder(srv.device, record, units=record_units) if record is not None else None
            if recorder is not None:
                await recorder.start()
                print(f"valve-emulator: recording to {', '.join(str(p) for p in recorder.paths.values())}",
                      flush=True)
            # Everything built so far (modules, compiled kernels, config) lives as long as the process: keep
            # it out of the cyclic GC, whose full passes over it would delay the tick by tens of ms.
            gc.freeze()
            try:
                if ready is not None:
                    ready(srv)
                await stop.wait()
            finally:
                if recorder is not None:
                    await recorder.stop()
    finally:
        for sig in handlers:
            try:
                loop.remove_signal_handler(sig)
            except (NotImplementedError, RuntimeError):
                pass


def run(args: argparse.Namespace) -> int:
    from valve_emulator.commands._config import load_server_or_default

    _check(args)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = apply_overrides(load_server_or_default(args.config), read_only=args.read_only,
                          max_connections=args.max_connections)
    units = [lp.device.unit for lp in cfg.loops]
    for u in args.record_unit or ():
        if u not in units:
            raise ValueError(f"--record-unit {u}: the device has units {units}")
    if args.uvloop:
        try:
            import uvloop
        except ImportError as exc:
            raise ValueError("--uvloop needs the uvloop package: pip install uvloop") from exc
        runner = uvloop.run
    else:
        runner = asyncio.run
    runner(serve(cfg, host=args.host, port=args.port, time_scale=args.time_scale, config_path=args.config,
                 record=args.record, record_units=args.record_unit, read_only=args.read_only,
                 max_connections=args.max_connections))
    print("valve-emulator: stopped", flush=True)
    return 0
