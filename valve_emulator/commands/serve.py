"""``valve-emulator serve [CONFIG] [--host 127.0.0.1] [--port 5020] [--time-scale X]``: run the device."""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
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
    p.add_argument("--port", type=int, default=5020, help="TCP port (default %(default)s; 0 picks a free port)")
    p.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                   help="simulated seconds per wall second (default %(default)s; same physics, faster clock)")
    p.add_argument("--uvloop", action="store_true", help="use uvloop's event loop (pip install uvloop)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def _check(args: argparse.Namespace) -> None:
    if not (0 <= args.port <= 65535):
        raise ValueError(f"--port must be 0..65535, got {args.port}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise ValueError(f"--time-scale must be a finite number > 0, got {args.time_scale}")


def _all_interfaces(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return host in ("", "*")


async def serve(config, *, host: str, port: int, time_scale: float, ready=None) -> None:
    """Serve until SIGINT/SIGTERM (or cancellation); ``ready(server)`` is called once listening."""
    from valve_emulator.device.server import EmulatorServer

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # not the main thread / not supported
            pass
    try:
        async with EmulatorServer(config, host=host, port=port, time_scale=time_scale) as srv:
            units = ", ".join(f"{u} ({lp.name})" for u, lp in zip(srv.units, config.loops))
            print(f"valve-emulator: listening on {host}:{srv.port}, unit ids {units}; tick {config.device.tick:g} s, "
                  f"time-scale {time_scale:g}; Ctrl-C stops", flush=True)
            if _all_interfaces(host):
                print("valve-emulator: WARNING: bound to all interfaces. Modbus TCP has no authentication: "
                      "anyone who can reach this port can move the valve. Use an isolated network.",
                      file=sys.stderr, flush=True)
            if ready is not None:
                ready(srv)
            await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.remove_signal_handler(sig)
            except (NotImplementedError, RuntimeError):
                pass


def run(args: argparse.Namespace) -> int:
    from valve_emulator.commands._config import load_server_or_default

    _check(args)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = load_server_or_default(args.config)
    if args.uvloop:
        try:
            import uvloop
        except ImportError as exc:
            raise ValueError("--uvloop needs the uvloop package: pip install uvloop") from exc
        runner = uvloop.run
    else:
        runner = asyncio.run
    runner(serve(cfg, host=args.host, port=args.port, time_scale=args.time_scale))
    print("valve-emulator: stopped", flush=True)
    return 0
