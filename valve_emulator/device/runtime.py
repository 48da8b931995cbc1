"""The device as a server process: what ``valve-emulator serve`` runs once its flags are parsed.

- :func:`load_server_or_default`: a server config file, or the embedded default device;
- :func:`apply_overrides` / :func:`with_device`: a config with the command line's device settings
  (``--read-only``, ``--max-connections``, ``--lockstep``, instructor writes) in every device section;
- :func:`reload_config`: re-read the config file on SIGHUP and apply its live settings to a running server;
- :func:`serve`: Modbus TCP (and optionally Modbus RTU on a serial line and Modbus/TCP Security) until
  SIGINT/SIGTERM, with a tick recorder and the services the caller attaches (the instructor station, OPC UA:
  they live above this layer).

The lines :func:`serve` prints on stdout (``listening on HOST:PORT, ...``, ``reloaded ...``) are what a
supervisor (``serve --processes N``, a test, an orchestrator) reads to know the server is up: the "listening"
line comes only once every requested port and device (Modbus TCP, RTU, Modbus/TCP Security and the attached
services: the station's web port, OPC UA) is open. A port in use or a serial device that cannot be opened is a
:class:`~valve_emulator.errors.UserError` naming the flag and the port (``--opcua 4840: address already in
use``), raised before anything is printed or recorded.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import gc
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractAsyncContextManager, AsyncExitStack
from importlib import resources
from pathlib import Path
from typing import Any

from valve_emulator.errors import UserError

__all__ = ["DEFAULT_DEVICE", "Attach", "apply_overrides", "describe_units", "load_server_or_default", "opening",
           "reload_config", "serve", "with_device"]

_log = logging.getLogger("valve_emulator.serve")

#: Services that run beside the Modbus server for as long as it runs: ``attach(server)`` is entered once the
#: server's own ports are open and left before it stops (e.g. the instructor station's HTTP pages, an OPC UA
#: server). Entering it opens the services' ports and yields the lines announcing them, which :func:`serve`
#: prints after its "listening" line. A service that fails while the server runs calls
#: ``server.request_stop()``: :func:`serve` then stops as at SIGTERM (the recording is closed).
Attach = Callable[[Any], AbstractAsyncContextManager[Sequence[str]]]
#: The embedded device served without a CONFIG (package data ``valve_emulator/data``).
DEFAULT_DEVICE = "default_device.yaml"


def load_server_or_default(path: Path | None):
    """``load_server(path)``, or the embedded default device when ``path`` is None; a ``device.register_map``
    whose tags the device refuses (an unknown tag, a writable tag in an input register) is refused here, at
    load, naming the file, line and key."""
    from valve_emulator.config import load_server
    from valve_emulator.device.registers.mapping import register_map_of

    if path is not None:
        config = load_server(path)
        register_map_of(config)
        return config
    with resources.as_file(resources.files("valve_emulator.data") / DEFAULT_DEVICE) as p:
        return load_server(p)


def with_device(config, **changes):
    """``config`` with ``changes`` to the device settings of the server and of every loop."""
    loops = tuple(dataclasses.replace(lp, device=dataclasses.replace(lp.device, **changes)) for lp in config.loops)
    return dataclasses.replace(config, device=dataclasses.replace(config.device, **changes), loops=loops)


def apply_overrides(config, *, read_only: bool = False, max_connections: int | None = None,
                    lockstep: bool = False):
    """``config`` with the command line's ``--read-only`` / ``--max-connections`` / ``--lockstep`` in every device
    section (a flag left at its default changes nothing)."""
    changes = {k: v for k, v in (("read_only", read_only or None), ("max_connections", max_connections),
                                 ("lockstep", lockstep or None)) if v is not None}
    return with_device(config, **changes) if changes else config


def reload_config(server, path: Path | None, *, read_only: bool = False,
                  max_connections: int | None = None, process: tuple[int, int] | None = None) -> bool:
    """Re-read ``path`` and apply its live settings to ``server``; ``False`` (logged, nothing changed) if bad.

    ``process = (index, count)``: the server runs that slice of the file (``--process-index``).
    """
    from valve_emulator.config import load_server
    from valve_emulator.config.layout import server_slice
    from valve_emulator.device.registers.mapping import register_map_of

    if path is None:
        _log.warning("config reload: no config file (serving the embedded default device); nothing to reload")
        return False
    try:
        config = load_server(path)
        register_map_of(config)   # refuse a bad map now, not when a restart applies it
        if process is not None:
            config = server_slice(config, *process)
        config = apply_overrides(config, read_only=read_only, max_connections=max_connections,
                                 lockstep=server.config.device.lockstep)   # --lockstep outlives a reload
    except UserError as exc:  # ConfigError names file, line and key
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


@contextlib.contextmanager
def opening(what: str, host: str | None = None) -> Iterator[None]:
    """Run the block that opens ``what`` (a flag and its port or serial device: ``--opcua 4840``) on ``host``; an
    ``OSError`` (address in use, no such device, no permission) becomes a ``UserError`` naming it, in one line:
    ``--opcua 4840: address already in use``. An address this machine does not have names ``--host`` instead."""
    try:
        yield
    except OSError as exc:
        if host is not None and exc.errno == errno.EADDRNOTAVAIL:
            what = f"--host {host}"
        raise UserError(f"{what}: {_reason(exc)}") from exc


def _reason(exc: OSError) -> str:
    """What went wrong, without the address the caller names already: ``address already in use``. The errno
    may sit on an error the raised one wraps (the serial line's)."""
    cause: BaseException | None = exc
    while cause is not None:
        if isinstance(cause, OSError) and isinstance(cause.errno, int):
            text = os.strerror(cause.errno)
            return text[:1].lower() + text[1:]
        cause = cause.__cause__ or cause.__context__
    return str(exc.strerror or exc)


class _Signals:
    """SIGINT/SIGTERM set ``stop``; :meth:`on` adds a handler; every handler is removed on exit. Where the loop
    cannot take signal handlers (not the main thread, Windows) nothing is installed."""

    def __init__(self, loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> None:
        self.loop = loop
        self.installed: list[int] = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.on(sig, stop.set)

    def on(self, sig: int, handler: Callable[[], Any]) -> None:
        try:
            self.loop.add_signal_handler(sig, handler)
            self.installed.append(sig)
        except (NotImplementedError, RuntimeError):  # not the main thread / not supported
            pass

    def remove(self) -> None:
        for sig in self.installed:
            with contextlib.suppress(NotImplementedError, RuntimeError):
                self.loop.remove_signal_handler(sig)


def _listening_line(srv, config, *, host: str, time_scale: float, process, rtu: str | None, framer: str) -> str:
    from valve_emulator.device.registers import STEP_ADDRESS

    who = f"process {process[0]}/{process[1]} " if process is not None else ""
    rtu_note = "" if framer == "socket" else "; the TCP port speaks RTU frames (RTU over TCP)"
    if rtu is not None:
        rtu_note += f"; Modbus RTU on {rtu} at {srv.serial_links[0].settings}"
    clock = (f"lockstep (no tick until a client writes step, holding {STEP_ADDRESS})" if srv.device.lockstep
             else f"time-scale {time_scale:g}")
    return (f"valve-emulator: {who}listening on {host}:{srv.port}, unit ids {describe_units(config)}; "
            f"tick {config.device.tick:g} s, {clock}{rtu_note}; Ctrl-C stops")


async def serve(config, *, host: str, port: int, time_scale: float, ready=None, config_path: Path | None = None,
                record: Path | None = None, record_units=None, read_only: bool = False,
                max_connections: int | None = None, process: tuple[int, int] | None = None,
                rtu: str | None = None, serial=None, framer: str = "socket", tls_port: int | None = None,
                tls_context=None, attach: Attach | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or cancellation); ``ready(server)`` is called once listening.

    Every port and device is opened before the "listening" line is printed and before ``record`` is created:
    one that cannot be opened is a ``UserError`` naming its flag, and nothing has been written.

    ``rtu`` (a serial device) with ``serial`` (:class:`~valve_emulator.device.rtu.SerialSettings`) serves the
    units on that line too; ``framer="rtu"`` makes the TCP port speak RTU frames. ``tls_port`` with
    ``tls_context`` (:func:`~valve_emulator.device.tls.server_context`) serves Modbus/TCP Security.
    ``attach(server)`` (:data:`Attach`) runs the caller's services beside it.

    SIGHUP reloads ``config_path`` (:func:`reload_config`); ``record`` records ``record_units`` (default
    all) with :class:`~valve_emulator.device.record.TickRecorder`. ``process = (index, count)`` names the
    slice this server runs (``config`` is already that slice).
    """
    from valve_emulator.device.guard import binds_all_interfaces
    from valve_emulator.device.record import TickRecorder

    stop = asyncio.Event()
    signals = _Signals(asyncio.get_running_loop(), stop)
    try:
        async with AsyncExitStack() as stack:
            srv = await _open_modbus(stack, config, host=host, port=port, time_scale=time_scale, framer=framer,
                                     rtu=rtu, serial=serial)
            notices = []
            srv.request_stop = stop.set
            if tls_port is not None:
                with opening(f"--tls-port {tls_port}", host):
                    bound = await srv.open_tls(tls_context, port=tls_port)
                notices.append(f"valve-emulator: Modbus/TCP Security (TLS, client certificates) on {host}:{bound}")
            if attach is not None:
                notices.extend(await stack.enter_async_context(attach(srv)))
            hup = getattr(signal, "SIGHUP", None)
            if hup is not None:  # installed before the "listening" line, which tells a supervisor we are up
                signals.on(hup, lambda: reload_config(srv, config_path, read_only=read_only,
                                                      max_connections=max_connections, process=process))
            print(_listening_line(srv, config, host=host, time_scale=time_scale, process=process, rtu=rtu,
                                  framer=framer), flush=True)
            if binds_all_interfaces(host):
                print("valve-emulator: WARNING: bound to all interfaces. Modbus TCP has no authentication: "
                      "anyone who can reach this port can move the valve. Use an isolated network.",
                      file=sys.stderr, flush=True)
            for line in notices:
                print(line, flush=True)
            if record is not None:
                recorder = TickRecorder(srv.device, record, units=record_units)
                await recorder.start()
                stack.push_async_callback(recorder.stop)
                print(f"valve-emulator: recording to {', '.join(str(p) for p in recorder.paths.values())}",
                      flush=True)
            # Everything built so far (modules, compiled kernels, config) lives as long as the process: keep
            # it out of the cyclic GC, whose full passes over it would delay the tick by tens of ms.
            gc.freeze()
            if ready is not None:
                ready(srv)
            await stop.wait()
    finally:
        signals.remove()


async def _open_modbus(stack: AsyncExitStack, config, *, host: str, port: int, time_scale: float, framer: str,
                       rtu: str | None, serial):
    """The :class:`~valve_emulator.device.server.EmulatorServer` on ``--port`` (and its serial line on
    ``--rtu``), entered into ``stack``; a port in use or a device that cannot be opened names its flag."""
    from valve_emulator.device.server import EmulatorServer

    with opening(f"--port {port}", host):
        srv = await stack.enter_async_context(
            EmulatorServer(config, host=host, port=port, time_scale=time_scale, framer=framer))
    if rtu is not None:
        with opening(f"--rtu {rtu}"):
            srv.open_serial(rtu, serial)
    return srv
