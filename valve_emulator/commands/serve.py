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

Start-up: the "listening on HOST:PORT" line is printed once every requested port and device is open (Modbus TCP,
``--rtu``, ``--tls-port``, ``--web``, ``--opcua``), then one line per further interface; a readiness check may
wait for it. A port in use is one error line naming the flag and the port (``--opcua 4840: address already in
use``), exit status 2, nothing printed on stdout and no recording started.

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
import contextlib
import logging
import math
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING

from valve_emulator.commands._files import user_files
from valve_emulator.errors import UserError

if TYPE_CHECKING:   # the device (numba's kernels) is imported when a server starts, not for --help
    from valve_emulator.device.runtime import Attach

NAME = "serve"
HELP = "serve the valve and process as a Modbus TCP (and RTU) device on a real-time tick"

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
                   help="token the instructor page and API require (this or --web-users when --host is not "
                        "loopback)")
    p.add_argument("--web-users", type=Path, metavar="USERS.yaml",
                   help="station users (HTTP Basic) with hashed passwords and a role each, the --opcua-users "
                        "format; anonymous visitors then only watch")
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
                   help="users with hashed passwords and a role each (viewer, operator, instructor or a custom role "
                        "of device.roles); without it anonymous clients are operators")
    g.add_argument("--opcua-pki", type=Path, metavar="DIR",
                   help="trust list of OPC UA client certificates: DIR/trusted/certs are accepted, unknown ones "
                        "are refused and copied to DIR/rejected/certs (default: opcua.pki, else the folder of "
                        "--opcua-cert)")
    g.add_argument("--opcua-trust-all", action="store_true",
                   help="accept every OPC UA client certificate (loopback --host only; for trying things out)")
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
        raise UserError(f"--port must be 0..65535, got {args.port}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise UserError(f"--time-scale must be a finite number > 0, got {args.time_scale}")
    if args.lockstep and args.time_scale != 1.0:
        raise UserError("--lockstep and --time-scale: in lockstep the client's step writes are the clock")
    if args.lockstep and args.processes > 1:
        raise UserError("--lockstep with --processes: each process would have its own clock; use one process")
    if args.max_connections is not None and not 1 <= args.max_connections <= 65535:
        raise UserError(f"--max-connections must be 1..65535, got {args.max_connections}")
    if args.record_unit and args.record is None:
        raise UserError("--record-unit needs --record FILE.csv")
    if args.processes < 1:
        raise UserError(f"--processes must be >= 1, got {args.processes}")
    if args.process_index is not None and not 0 <= args.process_index < args.processes:
        raise UserError(f"--process-index must be 0..{args.processes - 1} for --processes {args.processes}, "
                        f"got {args.process_index}")
    if args.processes > 1 and args.process_index is None and args.record is not None:
        raise UserError("--record with --processes: record in each process (--process-index) instead")
    if args.web is not None and not 0 <= args.web <= 65535:
        raise UserError(f"--web must be a port 0..65535, got {args.web}")
    if args.web is None and (args.web_token or args.snapshots or args.web_users):
        raise UserError("--web-token, --web-users and --snapshots need --web PORT")
    if args.web is not None and args.processes > 1:
        raise UserError("--web with --processes: the station serves one process's device; use --processes 1")
    if args.backtrack < 0 or not math.isfinite(args.backtrack):
        raise UserError(f"--backtrack must be >= 0 s, got {args.backtrack}")
    if args.web is not None and args.web_token is None and args.web_users is None:
        from valve_emulator.device.guard import is_loopback

        if not is_loopback(args.host):
            raise UserError(f"--web on --host {args.host} needs --web-token or --web-users: bound beyond loopback "
                            f"the instructor page and API must ask for credentials")
    if args.rtu is None and (args.baud, args.parity, args.stopbits) != (19200, "E", 1):
        raise UserError("--baud, --parity and --stopbits set up the serial line of --rtu DEVICE; give --rtu")
    if args.rtu is not None and args.processes > 1:
        raise UserError("--rtu serves one serial line from one process; it cannot be combined with --processes")
    _check_secure(args)
    if args.port and args.port + args.processes - 1 > 65535:
        raise UserError(f"--port {args.port} + --processes {args.processes} runs past port 65535")


def _check_secure(args: argparse.Namespace) -> None:
    """The OPC UA and Modbus/TLS flags: ports in range, the files each needs, one process."""
    for flag, port in (("--opcua", args.opcua), ("--tls-port", args.tls_port)):
        if port is not None and not 0 <= port <= 65535:
            raise UserError(f"{flag} must be a port 0..65535, got {port}")
        if port is not None and args.processes > 1:
            raise UserError(f"{flag} with --processes: it serves one process's loops; use --processes 1")
    if args.opcua_policy:
        from valve_emulator.config.schema import OPCUA_POLICIES

        for policy in args.opcua_policy:
            if policy not in OPCUA_POLICIES:
                raise UserError(f"--opcua-policy {policy!r}: one of {', '.join(OPCUA_POLICIES)}")


def opcua_settings(args: argparse.Namespace, config) -> tuple[int | None, object]:
    """The OPC UA port and :class:`~valve_emulator.opcua.OpcUaSecurity`: the flags over the config's ``opcua``
    section (files read and checked now); ``(None, None)`` without OPC UA."""
    sec = config.opcua
    port = args.opcua if args.opcua is not None else sec.port
    if port is None:
        for flag, given in (("--opcua-pki", args.opcua_pki), ("--opcua-trust-all", args.opcua_trust_all)):
            if given:
                raise UserError(f"{flag} needs OPC UA: give --opcua PORT (or the config's opcua.port)")
        return None, None
    from valve_emulator.opcua import OpcUaSecurity, load_users

    users_path = args.opcua_users or sec.users
    cert, key = args.opcua_cert or sec.certificate, args.opcua_key or sec.private_key
    for what, path in (("certificate", cert), ("private key", key)):
        if path is not None and not Path(path).is_file():
            raise UserError(f"opcua {what} {path}: no such file")
    from valve_emulator.device.roles import RoleTable

    roles = RoleTable.from_config(config)
    policies = tuple(args.opcua_policy or sec.policies)
    secure = any(p != "None" for p in policies)   # only a secure channel carries a client certificate
    security = OpcUaSecurity(policies=policies,
                             certificate=Path(cert) if cert else None, private_key=Path(key) if key else None,
                             users=load_users(users_path, roles) if users_path is not None else None,
                             pki=Path(args.opcua_pki or sec.pki or Path(cert or "pki/server.der").parent) if secure
                             else None,
                             trust_all=args.opcua_trust_all)
    security.check(args.host)
    return port, security


def web_users(args: argparse.Namespace, config) -> dict | None:
    """The station's users (``--web-users``) with roles of the config's permission table; None without."""
    if args.web_users is None:
        return None
    from valve_emulator.device.accounts import load_users
    from valve_emulator.device.roles import RoleTable

    return load_users(args.web_users, RoleTable.from_config(config))


def opcua_history_seconds(args: argparse.Namespace, opcua_port: int | None) -> float | None:
    """``--opcua-history`` in seconds (None without it); it needs OPC UA."""
    if args.opcua_history is None:
        return None
    if opcua_port is None:
        raise UserError("--opcua-history needs OPC UA: give --opcua PORT (or the config's opcua.port)")
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


def _services(args: argparse.Namespace, config, *, opcua: int | None, security,
              failures: list[str]) -> Attach | None:
    """The instructor station (``--web``) and OPC UA (``--opcua``) beside the Modbus server, sharing one
    :class:`~valve_emulator.station.core.Station` (the HTTP pages and the OPC UA methods act on the same one);
    None when neither is asked for. Entered, it opens their ports and yields the lines announcing them. A service
    that ends unasked (the OPC UA process) adds a line to ``failures`` and stops the server."""
    if args.web is None and opcua is None:
        return None

    @contextlib.asynccontextmanager
    async def attach(srv) -> AsyncIterator[list[str]]:
        async with contextlib.AsyncExitStack() as stack:
            yield await _start_services(srv, stack, args, config, opcua=opcua, security=security,
                                        failures=failures)

    return attach


async def _start_services(srv, stack: contextlib.AsyncExitStack, args: argparse.Namespace, config, *,
                          opcua: int | None, security, failures: list[str]) -> list[str]:
    """Make the station and start the web pages and OPC UA over it (their stops pushed on ``stack``); return the
    lines announcing them. If a port is taken, the ``--snapshots`` folder made for the station is removed again:
    a server that did not start leaves nothing behind."""
    from valve_emulator.device.snapshots import BacktrackRing, SnapshotStore
    from valve_emulator.station.core import Station

    made = args.snapshots is not None and not args.snapshots.exists()
    try:
        station = Station(srv.device, snapshots=SnapshotStore(args.snapshots),
                          backtrack=BacktrackRing(args.backtrack, 30) if args.backtrack > 0 else None)
        wanted = ((_start_web, args.web is not None), (_start_opcua, opcua is not None))
        lines = []
        for start in (start for start, asked in wanted if asked):
            stop, line = await start(srv, station, config, args, port=opcua, security=security, failures=failures)
            stack.push_async_callback(stop)
            lines.append(line)
        return lines
    except BaseException:
        if made:
            with contextlib.suppress(OSError):   # only if still empty
                args.snapshots.rmdir()
        raise


async def _start_web(srv, station, config, args: argparse.Namespace, **_: object):
    """Start the instructor ``station``'s HTTP pages on ``--host``:``--web``; return its stop and the line
    announcing its URL."""
    from valve_emulator.device.runtime import opening
    from valve_emulator.station.app import start_station

    users = web_users(args, config)
    with opening(f"--web {args.web}", args.host):
        runner, bound = await start_station(station, host=args.host, port=args.web, token=args.web_token,
                                            users=users)
    where = f"[{args.host}]" if ":" in args.host else args.host
    return runner.cleanup, (f"valve-emulator: instructor station at http://{where}:{bound}/ (trainee) and "
                            f"http://{where}:{bound}/instructor")


async def _start_opcua(srv, station, config, args: argparse.Namespace, *, port: int, security,
                       failures: list[str]):
    """Start the OPC UA server over ``srv``'s device (methods through ``station``) in a process of its own
    (:class:`~valve_emulator.opcua.OpcUaProcess`); return its stop and the line announcing its URL, printed
    once that process answers. A port in use is one error line. If the OPC UA process ends unasked, the server
    stops as at Ctrl-C (the recording is closed) and ``serve`` exits with status 1."""
    from valve_emulator.device.runtime import opening
    from valve_emulator.opcua import OpcUaProcess

    def ended(code: int | None) -> None:
        failures.append(f"the OPC UA process ended unexpectedly (exit code {code})")
        srv.request_stop()

    history = opcua_history_seconds(args, port)
    server = OpcUaProcess(srv.device, loops=config.loops, host=args.host, port=port, security=security,
                          station=station, history=history, on_exit=ended)
    with opening(f"--opcua {port}", args.host):
        await server.start()
    return server.stop, f"valve-emulator: OPC UA at {server.url} (policies {', '.join(server.security.policies)})"


def run(args: argparse.Namespace) -> int:
    _check(args)
    if args.processes > 1 and args.process_index is None:
        from valve_emulator.commands._processes import run_processes

        return run_processes(args)
    files = {"": args.config, "--record": args.record, "--snapshots": args.snapshots,
             "--opcua-cert": args.opcua_cert, "--opcua-key": args.opcua_key, "--opcua-users": args.opcua_users,
             "--opcua-pki": args.opcua_pki, "--web-users": args.web_users,
             "--tls-cert": args.tls_cert, "--tls-key": args.tls_key, "--tls-ca": args.tls_ca}
    with user_files(files):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.config.layout import server_slice
    from valve_emulator.device.runtime import apply_overrides, load_server_or_default, serve

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
        raise UserError("--record: recording needs one loop per unit id; this config puts several loops behind "
                        "a unit (fleet.loops_per_unit > 1)")
    for u in args.record_unit or ():
        if u not in units:
            raise UserError(f"--record-unit {u}: the device has units {units}")
    if args.uvloop:
        try:
            import uvloop
        except ImportError as exc:
            raise UserError("--uvloop needs the uvloop package: pip install uvloop") from exc
        runner = uvloop.run
    else:
        runner = asyncio.run
    port = args.port + args.process_index if args.port and process is not None else args.port
    serial = None
    if args.rtu is not None:
        from valve_emulator.device.rtu import SerialSettings

        serial = SerialSettings(baud=args.baud, parity=args.parity, stopbits=args.stopbits)
    web_users(args, cfg)   # refuse a bad users file before anything starts
    opcua_port, security = opcua_settings(args, cfg)
    opcua_history_seconds(args, opcua_port)  # refuse a bad --opcua-history before anything starts
    tls_port, tls_context = tls_settings(args, cfg)
    failures: list[str] = []
    runner(serve(cfg, host=args.host, port=port, time_scale=args.time_scale, config_path=args.config,
                 record=args.record, record_units=args.record_unit, read_only=args.read_only,
                 max_connections=args.max_connections, process=process, rtu=args.rtu, serial=serial,
                 framer=args.framer, tls_port=tls_port, tls_context=tls_context,
                 attach=_services(args, cfg, opcua=opcua_port, security=security, failures=failures)))
    if failures:
        print(f"valve-emulator: stopped: {failures[0]}", file=sys.stderr, flush=True)
        return 1
    print("valve-emulator: stopped", flush=True)
    return 0
