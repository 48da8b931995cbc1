"""The OPC UA server in a process of its own, fed from the device's register image: what ``serve --opcua`` runs.

:class:`OpcUaProcess` lives in the device process. It starts the OPC UA process
(``python -m valve_emulator.opcua``: a fresh interpreter, whatever the caller's main module, handed
its end of a socket pair and, as the first message, what to serve) and then:

- publishes the register image to shared memory whenever it changes
  (:class:`~valve_emulator.opcua.shared.ImagePublisher`, one copy per tick however many clients subscribe) and
  notes each tick and each alarm change to the OPC UA process;
- answers that process's calls -- a client's write, an alarm acknowledgement, a station method -- with a
  :class:`~valve_emulator.opcua.source.LocalSource` on the device: the same checks as in process, and the
  device's verdict goes back to the client (BadUserAccessDenied, BadOutOfRange, ...).

:meth:`OpcUaProcess.start` returns once the OPC UA process listens (its error, such as a port in use, is raised
here); the device is paused while that process builds its address space. If the OPC UA process ends without
being asked, the device process logs it with its exit code and calls ``on_exit(code)``
(``serve`` then stops cleanly: the recording is closed as at Ctrl-C, and exits with status 1). Stopping the
device process stops the OPC UA process: :meth:`stop` closes the channel, the OPC UA process stops its server
and exits (it is killed after :data:`STOP_TIMEOUT`); if the device process dies, the OPC UA process reads the end
of the channel and exits too.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import sys
from collections.abc import Callable, Sequence
from typing import Any

from valve_emulator.opcua.channel import Channel
from valve_emulator.opcua.remote import ChildSpec
from valve_emulator.opcua.server import OpcUaCounters, OpcUaSecurity
from valve_emulator.opcua.shared import ImagePublisher
from valve_emulator.opcua.source import LocalSource

__all__ = ["OpcUaProcess", "OpcUaProcessError", "STOP_TIMEOUT"]

_log = logging.getLogger(__name__)
#: Seconds the OPC UA process has to stop before it is killed.
STOP_TIMEOUT = 10.0


def _log_record(name: str, level: int, message: str, exc_text: str | None) -> None:
    """Log a record of the OPC UA process here, as this process's own (its ``processName`` says where from)."""
    logger = logging.getLogger(name)
    if logger.isEnabledFor(level):
        record = logger.makeRecord(name, level, "(OPC UA process)", 0, message, None, None)
        record.exc_text, record.processName = exc_text, "opcua"
        logger.handle(record)


class OpcUaProcessError(RuntimeError):
    """The OPC UA process ended before it listened, without saying why."""


class OpcUaProcess:
    """Serve ``device`` over OPC UA from a process of its own (see the module docstring); the same parameters
    as :class:`~valve_emulator.opcua.server.OpcUaServer`, with the device and its ``station`` in place of a
    source, and ``on_exit(exit_code)`` called if the OPC UA process ends unasked."""

    def __init__(self, device: Any, *, loops: Sequence[Any], host: str = "127.0.0.1", port: int = 0,
                 security: OpcUaSecurity | None = None, station: Any = None, history: float | None = None,
                 history_path: str = ":memory:", on_exit: Callable[[int | None], None] | None = None) -> None:
        self.device, self.loops, self.host, self.port = device, tuple(loops), host, int(port)
        self.security = security or OpcUaSecurity()
        self.security.check(host)   # refused here, before a process is started
        self.local = LocalSource(device, station)
        self.history, self.history_path, self.on_exit = history, history_path, on_exit
        self.process: asyncio.subprocess.Process | None = None
        self.publisher: ImagePublisher | None = None
        self.channel: Channel | None = None
        #: the OPC UA process's exit code once it ended unasked (None while it runs or after :meth:`stop`)
        self.exit_code: int | None = None
        self._reading: asyncio.Task | None = None
        self._watching: asyncio.Task | None = None
        self._answer: asyncio.Future | None = None
        self._noted = -1
        self._stopping = False

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}/valve-emulator/"

    # --- the device side ------------------------------------------------------------------------------

    def _published(self) -> None:
        """The image changed: copy it to shared memory; note a new tick to the OPC UA process."""
        self.publisher.publish()
        ticks = self.device.ticks
        if ticks != self._noted:
            self._noted = ticks
            self.channel.note("tick", ticks, self.device.period)

    def _alarmed(self, change: Any) -> None:
        self.channel.note("alarm", change)

    def _spec(self) -> ChildSpec:
        local, device = self.local, self.device
        return ChildSpec(shm_name=self.publisher.name, layout=self.publisher.layout, units=tuple(local.units),
                         offsets=local.offsets, scaling=local.scaling, dt=local.dt, period=device.period,
                         has_station=local.has_station, has_alarms=local.has_alarms,
                         raised=tuple(local.raised_alarms()), loops=self.loops, host=self.host, port=self.port,
                         security=self.security, history=self.history, history_path=self.history_path,
                         log_level=logging.getLogger().getEffectiveLevel())

    # --- lifecycle ------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the OPC UA process and return once it listens (:attr:`port` is then its port)."""
        loop = asyncio.get_running_loop()
        self._answer = loop.create_future()
        ours, theirs = socket.socketpair()
        local = self.local
        self.channel = Channel(ours, {"write": local.write, "acknowledge_alarm": local.acknowledge_alarm,
                                      "station_action": local.station_action, "ready": self._ready,
                                      "failed": self._failed, "log": _log_record})
        await self.channel.open()
        self._reading = loop.create_task(self.channel.run(), name="valve-emulator-opcua-channel")
        try:
            async with local.paused():
                self.publisher = ImagePublisher(self.device)
                self.channel.note("spec", self._spec())   # the first message: what to serve
                self._published()
                self.device.image_listeners.append(self._published)
                local.alarm_listeners.append(self._alarmed)
                self.process = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "valve_emulator.opcua", str(theirs.fileno()),
                    pass_fds=(theirs.fileno(),), stdin=asyncio.subprocess.DEVNULL)
                theirs.close()
                self._watching = loop.create_task(self._watch(), name="valve-emulator-opcua-watch")
                self.port = await self._answer
        except BaseException:
            await self.stop()
            raise
        _log.info("OPC UA process %d on %s:%d", self.process.pid, self.host, self.port)

    def _ready(self, port: int) -> None:
        if not self._answer.done():
            self._answer.set_result(int(port))

    def _failed(self, exc: BaseException) -> None:
        if not self._answer.done():
            self._answer.set_exception(exc)

    async def _watch(self) -> None:
        """Wait for the OPC UA process to end: before it listened, an error of :meth:`start`; unasked, logged
        and ``on_exit``."""
        code = await self.process.wait()
        if self._answer is not None and not self._answer.done():
            self._answer.set_exception(OpcUaProcessError(f"the OPC UA process ended before it listened "
                                                         f"(exit code {code})"))
            return
        if self._stopping:
            return
        self.exit_code = code
        _log.error("the OPC UA process (pid %d) ended unexpectedly with exit code %s; OPC UA clients are "
                   "disconnected", self.process.pid, code)
        if self.on_exit is not None:
            self.on_exit(code)

    async def counters(self) -> OpcUaCounters:
        """The OPC UA process's counters (:class:`~valve_emulator.opcua.server.OpcUaCounters`)."""
        return await self.channel.call("counters")

    async def stop(self) -> None:
        """Stop the OPC UA process (closing the channel asks it to; killed after :data:`STOP_TIMEOUT`) and stop
        publishing."""
        self._stopping = True
        with contextlib.suppress(ValueError):
            self.device.image_listeners.remove(self._published)
        with contextlib.suppress(ValueError):
            self.local.alarm_listeners.remove(self._alarmed)
        if self.channel is not None:
            await self.channel.close()
        if self._reading is not None:
            self._reading.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reading
        process = self.process
        if process is not None and process.returncode is None:
            try:
                await asyncio.wait_for(asyncio.shield(process.wait()), STOP_TIMEOUT)
            except TimeoutError:
                _log.error("the OPC UA process (pid %d) did not stop within %g s: killed", process.pid,
                           STOP_TIMEOUT)
                process.kill()
                await process.wait()
        if self._watching is not None:
            self._watching.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watching
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None

    async def __aenter__(self) -> OpcUaProcess:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()
