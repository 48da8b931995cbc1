"""``valve-emulator serve [CONFIG] [--host 127.0.0.1] [--port 5020] [--time-scale X]``: run the device.

``--web PORT`` also serves the instructor station (browser HMI at ``/``, instructor page at ``/instructor``,
HTTP API under ``/api``; ``docs/station.md``) in the same event loop, on the same host; ``--web 0`` picks a
free port. Bound to another address than loopback it needs ``--web-token``. ``--snapshots DIR`` keeps the
station's named snapshots as files there, so they survive a restart.

Modbus RTU: ``--rtu DEVICE [--baud 19200] [--parity E|O|N] [--stopbits 1|2]`` serves the same units on a
serial line as well (default 19200 8E1, the serial line specification's default), from the same process
and tick as the TCP port; ``--framer rtu`` makes the TCP port speak RTU frames instead of Modbus TCP (RTU
over TCP, as gateways do).

Lockstep: ``--lockstep`` (or ``device.lockstep: true`` in CONFIG) runs no tick by itself: a client writes N to the
``step`` register (holding 65296, every unit id) and the device runs N ticks before it answers that write, so a
PLC program in any language closes the loop deterministically (read PV, compute, write OP, write step;
docs/testing.md). The station's ``POST /api/step`` does the same.

SIGINT/SIGTERM stop it (a recording is complete up to the last tick: every row is flushed as written).
SIGHUP re-reads CONFIG and applies its connection and access settings (``device.read_only``,
``instructor_*``, ``max_connections``, ``idle_timeout``, ``frame_timeout``, ``error_rate``) at once; other
changes are reported as needing a restart, and an invalid file keeps the running config and logs why.
``--read-only`` and ``--max-connections`` win over the file, also after a reload.

Several processes (plant-size fleets, ``docs/deployment.md``): ``--processes N --process-index I`` serves
slice ``I`` of the config's loops (whole units, :func:`valve_emulator.config.layout.partition`) on port
``PORT + I``; this is what an orchestrator starts once per process or machine. ``--processes N`` alone is
the same N processes started by this one: the parent prints which port holds which units, forwards
SIGINT/SIGTERM/SIGHUP to them, and stops them all within a second (a process that does not stop in time
is killed). If one of them exits on its own, the parent stops the others and exits with status 1.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import logging
import math
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

NAME = "serve"
HELP = "serve the valve and process as a Modbus TCP (and RTU) device on a real-time tick"

_log = logging.getLogger("valve_emulator.serve")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="?", metavar="CONFIG",
                   help="server or loop config (default: the concentration loop of Choudhury, Thornhill & Shah, "
                        "sticky valve, external controller)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default %(default)s; 0.0.0.0 = all interfaces)")
    from valve_emulator.device.registers import DEFAULT_PORT

    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (default %(default)s; 0 picks a free port)")
    p.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                   help="simulated seconds per wall second (default %(default)s; same physics, faster clock)")
    p.add_argument("--lockstep", action="store_true",
                   help="no tick runs by itself: a client writes N to the step register (holding 65296) to run N "
                        "ticks, answered once they have run (device.lockstep)")
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
    p.add_argument("--web", type=int, metavar="PORT",
                   help="also serve the instructor station over HTTP on this port of the same host (0: a free "
                        "port); see docs/station.md")
    p.add_argument("--web-token", metavar="TOKEN",
                   help="token the instructor page and API require (needed when --host is not loopback)")
    p.add_argument("--snapshots", type=Path, metavar="DIR",
                   help="directory of the station's named snapshots (created if missing; default: in memory)")
    p.add_argument("--backtrack", type=float, default=60.0, metavar="S",
                   help="station backtrack: a snapshot every S simulated seconds, the last 30 kept "
                        "(default %(default)s; 0 turns it off)")
    g = p.add_argument_group("Modbus RTU")
    g.add_argument("--rtu", metavar="DEVICE", help="also serve the units on this serial device (e.g. /dev/ttyUSB0)")
    g.add_argument("--baud", type=int, default=19200, help="serial line baud rate (default %(default)s)")
    g.add_argument("--parity", choices=("E", "O", "N"), default="E", help="parity (default %(default)s)")
    g.add_argument("--stopbits", type=int, choices=(1, 2), default=1, help="stop bits (default %(default)s)")
    g.add_argument("--framer", choices=("socket", "rtu"), default="socket",
                   help="what the TCP port speaks: socket = Modbus TCP (default), rtu = RTU frames over TCP")
    g = p.add_argument_group("OPC UA and Modbus/TCP Security (docs/opcua.md)")
    g.add_argument("--opcua", type=int, metavar="PORT",
                   help="also serve the loops over OPC UA on this port (4840 by convention; 0 picks a free port)")
    g.add_argument("--opcua-policy", action="append", metavar="POLICY", default=None,
                   help="OPC UA security policy: None, Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss "
                        "(Sign&Encrypt; repeatable; default None, loopback only)")
    g.add_argument("--opcua-cert", type=Path, metavar="CERT",
                   help="OPC UA application certificate (valve-emulator certs --opcua DIR)")
    g.add_argument("--opcua-key", type=Path, metavar="KEY", help="its private key")
    g.add_argument("--opcua-users", type=Path, metavar="USERS.yaml",
                   help="users with hashed passwords and a role each (operator, instructor); without it anonymous "
                        "clients are operators")
    g.add_argument("--opcua-history", metavar="DURATION",
                   help="keep the last DURATION (600, 600s, 10m, 2h) of every loop's PV, OP, SP and MV for OPC UA "
                        "HistoryRead (in memory, asyncua's SQLite history)")
    g.add_argument("--tls-port", type=int, metavar="PORT",
                   help="also serve Modbus/TCP Security (TLS, mutual authentication, roles) on this port "
                        "(802 by convention; 0 picks a free port)")
    g.add_argument("--tls-cert", type=Path, metavar="CERT", help="the TLS server certificate (PEM)")
    g.add_argument("--tls-key", type=Path, metavar="KEY", help="its private key (PEM)")
    g.add_argument("--tls-ca", type=Path, metavar="CA", help="the CA that signs client certificates (PEM)")
    p.add_argument("--processes", type=int, default=1, metavar="N",
                   help="split the loops over N server processes on ports PORT..PORT+N-1, each owning whole "
                        "units (default 1; one per core)")
    p.add_argument("--process-index", type=int, metavar="I",
                   help="serve only slice I (0..N-1) of --processes N, on port PORT+I (for an orchestrator "
                        "that starts each process itself)")


def _check(args: argparse.Namespace) -> None:
    if not (0 <= args.port <= 65535):
        raise ValueError(f"--port must be 0..65535, got {args.port}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise ValueError(f"--time-scale must be a finite number > 0, got {args.time_scale}")
    if args.lockstep and args.time_scale != 1.0:
        raise ValueError("--lockstep and --time-scale: in lockstep the client's step writes are the clock")
    if args.lockstep and args.processes > 1:
        raise ValueError("--lockstep with --processes: each process would have its own clock; use one process")
    if args.max_connections is not None and not 1 <= args.max_connections <= 65535:
        raise ValueError(f"--max-connections must be 1..65535, got {args.max_connections}")
    if args.record_unit and args.record is None:
        raise ValueError("--record-unit needs --record FILE.csv")
    if args.processes < 1:
        raise ValueError(f"--processes must be >= 1, got {args.processes}")
    if args.process_index is not None and not 0 <= args.process_index < args.processes:
        raise ValueError(f"--process-index must be 0..{args.processes - 1} for --processes {args.processes}, "
                         f"got {args.process_index}")
    if args.processes > 1 and args.process_index is None and args.record is not None:
        raise ValueError("--record with --processes: record in each process (--process-index) instead")
    if args.web is not None and not 0 <= args.web <= 65535:
        raise ValueError(f"--web must be a port 0..65535, got {args.web}")
    if args.web is None and (args.web_token or args.snapshots):
        raise ValueError("--web-token and --snapshots need --web PORT")
    if args.web is not None and args.processes > 1:
        raise ValueError("--web with --processes: the station serves one process's device; use --processes 1")
    if args.backtrack < 0 or not math.isfinite(args.backtrack):
        raise ValueError(f"--backtrack must be >= 0 s, got {args.backtrack}")
    if args.web is not None and args.web_token is None:
        from valve_emulator.device.guard import is_loopback

        if not is_loopback(args.host):
            raise ValueError(f"--web on --host {args.host} needs --web-token: bound beyond loopback the instructor "
                             f"page and API must ask for a token")
    if args.rtu is None and (args.baud, args.parity, args.stopbits) != (19200, "E", 1):
        raise ValueError("--baud, --parity and --stopbits set up the serial line of --rtu DEVICE; give --rtu")
    if args.rtu is not None and args.processes > 1:
        raise ValueError("--rtu serves one serial line from one process; it cannot be combined with --processes")
    _check_secure(args)
    if args.port and args.port + args.processes - 1 > 65535:
        raise ValueError(f"--port {args.port} + --processes {args.processes} runs past port 65535")


def _check_secure(args: argparse.Namespace) -> None:
    """The OPC UA and Modbus/TLS flags: ports in range, the files each needs, one process."""
    for flag, port in (("--opcua", args.opcua), ("--tls-port", args.tls_port)):
        if port is not None and not 0 <= port <= 65535:
            raise ValueError(f"{flag} must be a port 0..65535, got {port}")
        if port is not None and args.processes > 1:
            raise ValueError(f"{flag} with --processes: it serves one process's loops; use --processes 1")
    if args.opcua_policy:
        from valve_emulator.config.schema import OPCUA_POLICIES

        for policy in args.opcua_policy:
            if policy not in OPCUA_POLICIES:
                raise ValueError(f"--opcua-policy {policy!r}: one of {', '.join(OPCUA_POLICIES)}")


def opcua_settings(args: argparse.Namespace, config) -> tuple[int | None, object]:
    """The OPC UA port and :class:`~valve_emulator.opcua.OpcUaSecurity`: the flags over the config's ``opcua``
    section (files read and checked now); ``(None, None)`` without OPC UA."""
    sec = config.opcua
    port = args.opcua if args.opcua is not None else sec.port
    if port is None:
        return None, None
    from valve_emulator.opcua import OpcUaSecurity, load_users

    users_path = args.opcua_users or sec.users
    cert, key = args.opcua_cert or sec.certificate, args.opcua_key or sec.private_key
    for what, path in (("certificate", cert), ("private key", key)):
        if path is not None and not Path(path).is_file():
            raise ValueError(f"opcua {what} {path}: no such file")
    security = OpcUaSecurity(policies=tuple(args.opcua_policy or sec.policies),
                             certificate=Path(cert) if cert else None, private_key=Path(key) if key else None,
                             users=load_users(users_path) if users_path is not None else None)
    security.check(args.host)
    return port, security


def opcua_history_seconds(args: argparse.Namespace, opcua_port: int | None) -> float | None:
    """``--opcua-history`` in seconds (None without it); it needs OPC UA."""
    if args.opcua_history is None:
        return None
    if opcua_port is None:
        raise ValueError("--opcua-history needs OPC UA: give --opcua PORT (or the config's opcua.port)")
    from valve_emulator.opcua.history import history_seconds

    return history_seconds(args.opcua_history)


def tls_settings(args: argparse.Namespace, config) -> tuple[int | None, object]:
    """The Modbus/TCP Security port and its TLS context: the flags over the config's ``tls`` section."""
    sec = config.tls
    port = args.tls_port if args.tls_port is not None else sec.port
    if port is None:
        return None, None
    from valve_emulator.device.tls import server_context

    return port, server_context(args.tls_cert or sec.certificate, args.tls_key or sec.private_key,
                                args.tls_ca or sec.ca)


def apply_overrides(config, *, read_only: bool = False, max_connections: int | None = None,
                    lockstep: bool = False):
    """``config`` with the command line's ``--read-only`` / ``--max-connections`` / ``--lockstep`` in every device
    section."""
    changes = {k: v for k, v in (("read_only", read_only or None), ("max_connections", max_connections),
                                 ("lockstep", lockstep or None)) if v is not None}
    return with_device(config, **changes) if changes else config


def with_device(config, **changes):
    """``config`` with ``changes`` to the device settings of the server and of every loop."""
    loops = tuple(dataclasses.replace(lp, device=dataclasses.replace(lp.device, **changes)) for lp in config.loops)
    return dataclasses.replace(config, device=dataclasses.replace(config.device, **changes), loops=loops)


def reload_config(server, path: Path | None, *, read_only: bool = False,
                  max_connections: int | None = None, process: tuple[int, int] | None = None) -> bool:
    """Re-read ``path`` and apply its live settings to ``server``; ``False`` (logged, nothing changed) if bad.

    ``process = (index, count)``: the server runs that slice of the file (``--process-index``).
    """
    from valve_emulator.config import load_server
    from valve_emulator.config.layout import server_slice

    if path is None:
        _log.warning("config reload: no config file (serving the embedded default device); nothing to reload")
        return False
    try:
        config = load_server(path)
        if process is not None:
            config = server_slice(config, *process)
        config = apply_overrides(config, read_only=read_only, max_connections=max_connections,
                                 lockstep=server.config.device.lockstep)   # --lockstep outlives a reload
    except (ValueError, OSError) as exc:  # ConfigError is a ValueError and names file, line and key
        _log.error("config reload failed, keeping the running config: %s", exc)
        return False
    restart = server.reconfigure(config)
    later = f"; needs a restart to apply: {', '.join(restart)}" if restart else ""
    print(f"valve-emulator: reloaded {path}{later}", flush=True)
    return True


def describe_units(config) -> str:
    """The unit ids of ``config`` for the "listening" line: each with its loop's name, or a summary for fleets."""
    from valve_emulator.config.layout import unit_ranges

    units = list(dict.fromkeys(lp.device.unit for lp in config.loops))
    n = len(config.loops)
    if n == len(units) and n <= 32:
        return ", ".join(f"{lp.device.unit} ({lp.name})" for lp in config.loops)
    per_unit = max(lp.device.block for lp in config.loops) + 1
    return f"{unit_ranges(units)} ({n:,} loops" + (f", up to {per_unit} per unit)" if per_unit > 1 else ")")


async def serve(config, *, host: str, port: int, time_scale: float, ready=None, config_path: Path | None = None,
                record: Path | None = None, record_units=None, read_only: bool = False,
                max_connections: int | None = None, process: tuple[int, int] | None = None,
                web: int | None = None, web_token: str | None = None, snapshots: Path | None = None,
                backtrack: float = 60.0, rtu: str | None = None, serial=None, framer: str = "socket",
                opcua: int | None = None, opcua_security=None, tls_port: int | None = None,
                tls_context=None, opcua_history: float | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or cancellation); ``ready(server)`` is called once listening.

    ``web``: also serve the instructor station on that port (:func:`start_web`).
    ``rtu`` (a serial device) with ``serial`` (:class:`~valve_emulator.device.rtu.SerialSettings`) serves the
    units on that line too; ``framer="rtu"`` makes the TCP port speak RTU frames.

    ``opcua`` (a port) also serves the loops over OPC UA with ``opcua_security`` (and ``opcua_history``
    seconds of history); ``tls_port`` with
    ``tls_context`` (:func:`~valve_emulator.device.tls.server_context`) serves Modbus/TCP Security.

    SIGHUP reloads ``config_path`` (:func:`reload_config`); ``record`` records ``record_units`` (default
    all) with :class:`~valve_emulator.device.record.TickRecorder`. ``process = (index, count)`` names the
    slice this server runs (``config`` is already that slice).
    """
    from valve_emulator.device.guard import binds_all_interfaces
    from valve_emulator.device.record import TickRecorder
    from valve_emulator.device.registers import STEP_ADDRESS
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
        async with EmulatorServer(config, host=host, port=port, time_scale=time_scale, framer=framer) as srv:
            if rtu is not None:
                srv.open_serial(rtu, serial)
            hup = getattr(signal, "SIGHUP", None)
            if hup is not None:  # installed before the "listening" line, which tells a supervisor we are up
                handlers[hup] = lambda: reload_config(srv, config_path, read_only=read_only,
                                                      max_connections=max_connections, process=process)
                try:
                    loop.add_signal_handler(hup, handlers[hup])
                except (NotImplementedError, RuntimeError):
                    pass
            who = f"process {process[0]}/{process[1]} " if process is not None else ""
            rtu_note = "" if framer == "socket" else "; the TCP port speaks RTU frames (RTU over TCP)"
            if rtu is not None:
                rtu_note += f"; Modbus RTU on {rtu} at {srv.serial_links[0].settings}"
            clock = (f"lockstep (no tick until a client writes step, holding {STEP_ADDRESS})" if srv.device.lockstep
                     else f"time-scale {time_scale:g}")
            print(f"valve-emulator: {who}listening on {host}:{srv.port}, unit ids {describe_units(config)}; "
                  f"tick {config.device.tick:g} s, {clock}{rtu_note}; Ctrl-C stops", flush=True)
            if binds_all_interfaces(host):
                print("valve-emulator: WARNING: bound to all interfaces. Modbus TCP has no authentication: "
                      "anyone who can reach this port can move the valve. Use an isolated network.",
                      file=sys.stderr, flush=True)
            if tls_port is not None:
                bound = await srv.open_tls(tls_context, port=tls_port)
                print(f"valve-emulator: Modbus/TCP Security (TLS, client certificates) on {host}:{bound}", flush=True)
            station_runner = opcua_server = station = None
            if web is not None or opcua is not None:
                station = make_station(srv, snapshots=snapshots, backtrack=backtrack)
            if web is not None:
                station_runner = await start_web(station, host=host, port=web, token=web_token)
            if opcua is not None:
                opcua_server = await start_opcua(srv, station, config, host=host, port=opcua,
                                                 security=opcua_security, history=opcua_history)
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
                if opcua_server is not None:
                    await opcua_server.stop()
                if station_runner is not None:
                    await station_runner.cleanup()
    finally:
        for sig in handlers:
            try:
                loop.remove_signal_handler(sig)
            except (NotImplementedError, RuntimeError):
                pass


def make_station(srv, *, snapshots: Path | None, backtrack: float):
    """The instructor station over ``srv``'s device, shared by the HTTP pages and the OPC UA methods."""
    from valve_emulator.device.snapshots import BacktrackRing, SnapshotStore
    from valve_emulator.station.core import Station

    return Station(srv.device, snapshots=SnapshotStore(snapshots),
                   backtrack=BacktrackRing(backtrack, 30) if backtrack > 0 else None)


async def start_opcua(srv, station, config, *, host: str, port: int, security, history: float | None = None):
    """Start the OPC UA server over ``srv``'s device (methods through ``station``); print its URL; return it."""
    from valve_emulator.opcua import OpcUaServer

    server = OpcUaServer(srv.device, loops=config.loops, host=host, port=port, security=security, station=station,
                         history=history)
    await server.start()
    print(f"valve-emulator: OPC UA at {server.url} (policies {', '.join(server.security.policies)})", flush=True)
    return server


async def start_web(station, *, host: str, port: int, token: str | None):
    """Start the instructor ``station``'s HTTP pages on ``host:port``; print its URL; return its runner."""
    from valve_emulator.station.app import start_station

    runner, bound = await start_station(station, host=host, port=port, token=token)
    where = f"[{host}]" if ":" in host else host
    print(f"valve-emulator: instructor station at http://{where}:{bound}/ (trainee) and "
          f"http://{where}:{bound}/instructor", flush=True)
    return runner


def run(args: argparse.Namespace) -> int:
    from valve_emulator.commands._config import load_server_or_default
    from valve_emulator.config.layout import server_slice

    _check(args)
    if args.processes > 1 and args.process_index is None:
        return run_processes(args)
    process = None if args.process_index is None else (args.process_index, args.processes)
    fmt = "%(asctime)s %(levelname)s %(name)s: %(message)s"
    if process is not None:
        fmt = f"%(asctime)s %(levelname)s [process {process[0]}] %(name)s: %(message)s"
    logging.basicConfig(level=args.log_level, format=fmt)
    cfg = load_server_or_default(args.config)
    if process is not None:
        cfg = server_slice(cfg, *process)
    cfg = apply_overrides(cfg, read_only=args.read_only, max_connections=args.max_connections,
                          lockstep=args.lockstep)
    units = [lp.device.unit for lp in cfg.loops]
    if args.record is not None and any(lp.device.block for lp in cfg.loops):
        raise ValueError("--record: recording needs one loop per unit id; this config puts several loops behind "
                         "a unit (fleet.loops_per_unit > 1)")
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
    port = args.port + args.process_index if args.port and process is not None else args.port
    serial = None
    if args.rtu is not None:
        from valve_emulator.device.rtu import SerialSettings

        serial = SerialSettings(baud=args.baud, parity=args.parity, stopbits=args.stopbits)
    opcua_port, security = opcua_settings(args, cfg)
    opcua_history = opcua_history_seconds(args, opcua_port)
    tls_port, tls_context = tls_settings(args, cfg)
    runner(serve(cfg, host=args.host, port=port, time_scale=args.time_scale, config_path=args.config,
                 record=args.record, record_units=args.record_unit, read_only=args.read_only,
                 max_connections=args.max_connections, process=process, web=args.web,
                 web_token=args.web_token, snapshots=args.snapshots, backtrack=args.backtrack,
                 rtu=args.rtu, serial=serial, framer=args.framer, opcua=opcua_port,
                 opcua_security=security, tls_port=tls_port, tls_context=tls_context, opcua_history=opcua_history))
    print("valve-emulator: stopped", flush=True)
    return 0


# --- several processes started by this one ----------------------------------------------------------------

_LISTENING = re.compile(r"listening on (\S+):(\d+),")
#: Seconds the parent gives its processes to stop before it kills them (the whole stop stays under 1 s).
STOP_GRACE = 0.8


def _child_argv(args: argparse.Namespace, index: int) -> list[str]:
    argv = [sys.executable, "-m", "valve_emulator", "serve", str(args.config), "--processes", str(args.processes),
            "--process-index", str(index), "--host", args.host, "--port", str(args.port),
            "--time-scale", repr(args.time_scale), "--log-level", args.log_level]
    if args.uvloop:
        argv.append("--uvloop")
    if args.read_only:
        argv.append("--read-only")
    if args.max_connections is not None:
        argv += ["--max-connections", str(args.max_connections)]
    return argv


def run_processes(args: argparse.Namespace) -> int:
    """Start ``args.processes`` slices as child processes, print the layout, supervise and stop them."""
    from valve_emulator.commands._config import load_server_or_default
    from valve_emulator.config.layout import partition

    if args.config is None:
        raise ValueError("--processes needs a CONFIG with at least that many unit ids")
    config = load_server_or_default(args.config)   # fail here, once, rather than in N children
    slices = partition(config, args.processes)
    total, tick = len(config.loops), config.device.tick
    del config
    events: queue.Queue = queue.Queue()
    procs = [subprocess.Popen(_child_argv(args, i), stdout=subprocess.PIPE, text=True, bufsize=1)
             for i in range(args.processes)]

    def relay(i: int, proc: subprocess.Popen) -> None:
        listening = False
        for line in proc.stdout:
            m = None if listening else _LISTENING.search(line)
            if m:
                listening = True
                events.put(("ready", i, (m.group(1), int(m.group(2)))))
            else:
                print(f"[process {i}] {line}", end="", flush=True)
        events.put(("exit", i, None))

    relays = [threading.Thread(target=relay, args=(i, proc), daemon=True, name=f"serve-relay-{i}")
              for i, proc in enumerate(procs)]
    for thread in relays:
        thread.start()
    forwarded = (signal.SIGINT, signal.SIGTERM) + ((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ())
    previous = {sig: signal.signal(sig, lambda sig, _frame: events.put(("signal", sig, None))) for sig in forwarded}
    hup = getattr(signal, "SIGHUP", None)
    ready: dict[int, tuple[str, int]] = {}
    status = 0
    try:
        while True:
            try:
                kind, i, info = events.get(timeout=0.5)   # a timeout keeps the signal handlers responsive
            except queue.Empty:
                continue
            if kind == "ready":
                ready[i] = info
                if len(ready) == len(procs):
                    print(f"valve-emulator: {len(procs)} processes serve {total:,} loops; tick {tick:g} s, "
                          f"time-scale {args.time_scale:g}; Ctrl-C stops", flush=True)
                    for p, part in enumerate(slices):
                        host, port = ready[p]
                        print(f"valve-emulator: process {p} (pid {procs[p].pid}) listening on {host}:{port}, "
                              f"{part.describe()}", flush=True)
            elif kind == "signal" and i == hup:   # reload: each process re-reads the file itself
                for proc in procs:
                    if proc.poll() is None:
                        proc.send_signal(i)
            elif kind == "signal":
                break
            else:  # a process ended although nobody asked it to
                code = procs[i].wait()
                print(f"valve-emulator: process {i} exited with status {code}; stopping the others",
                      file=sys.stderr, flush=True)
                status = 1
                break
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _stop_all(procs)
        for thread in relays:   # let the processes' last lines out before ours
            thread.join(timeout=0.1)
    print("valve-emulator: stopped", flush=True)
    return status


def _stop_all(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every running child, wait up to :data:`STOP_GRACE` s in total, then kill the rest."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    deadline = time.monotonic() + STOP_GRACE
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
