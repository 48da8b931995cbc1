"""The OPC UA process: :func:`child_main` runs an :class:`~valve_emulator.opcua.server.OpcUaServer` over a
:class:`RemoteSource`, the device as shared memory and a channel to the device process show it.

- Values come from the :class:`~valve_emulator.opcua.shared.ImageReader`: a read copies the latest published
  image once (only if a new one was published since), so a read sees a write or a lockstep step at once, as
  in process: the device publishes before it answers.
- The device process notes every tick (``tick``) and every alarm change (``alarm``); the publisher waits for
  the first, the alarm conditions listen to the second.
- Writes, alarm acknowledgements and the station's actions are calls to the device process, where a
  :class:`~valve_emulator.opcua.source.LocalSource` runs them on the device with the same checks as in process;
  their refusals come back as the same exceptions.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import heapq
import itertools
import logging
import os
import pickle
import signal
import socket
import threading
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from valve_emulator.device.alarms import AlarmChange
from valve_emulator.opcua.channel import Channel, read_first
from valve_emulator.opcua.shared import COMPUTED, ImageReader, SharedLayout, TickImage

__all__ = ["ChildSpec", "RemoteSource", "child_main"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChildSpec:
    """Everything the OPC UA process needs to build its server: the shared block, the device's static shape,
    the alarms raised when it started, and the server's settings."""

    shm_name: str
    layout: SharedLayout
    units: tuple[int, ...]
    offsets: Any
    scaling: Any
    dt: float
    period: float
    has_station: bool
    has_alarms: bool
    raised: tuple[AlarmChange, ...]
    loops: tuple[Any, ...]
    host: str
    port: int
    security: Any
    history: float | None
    history_path: str
    log_level: int


class RemoteSource:
    """The :class:`~valve_emulator.opcua.source.DeviceSource` of the OPC UA process (see the module docstring)."""

    def __init__(self, spec: ChildSpec, channel: Channel | None = None) -> None:
        self.reader = ImageReader(spec.shm_name, spec.layout)
        self.channel = channel
        self.units, self.offsets, self.scaling = spec.units, spec.offsets, spec.scaling
        self.dt, self._period = spec.dt, spec.period
        self.has_station, self.has_alarms = spec.has_station, spec.has_alarms
        self.alarm_listeners: list[Callable[[AlarmChange], None]] = []
        self._alarms: dict[int, AlarmChange] = {c.index: c for c in spec.raised}
        self._waiters: list[tuple[int, int, asyncio.Future]] = []
        self._seq = itertools.count()
        self._rows = {quantity: row for row, quantity in enumerate(COMPUTED)}

    # --- values ---------------------------------------------------------------------------------------

    @property
    def image(self) -> bytes:
        return self.reader.read().image

    @property
    def ticks(self) -> int:
        return self.reader.read().ticks

    @property
    def sample_time(self) -> float:
        return self.reader.read().sample_time

    @property
    def period(self) -> float:
        return self._period

    @property
    def tick_time(self) -> float:
        """When the device ran the tick of the image (POSIX seconds, the device process's clock)."""
        return self.reader.read().wall_time

    def sampling(self, tick: int | None = None) -> contextlib.AbstractContextManager[Any]:
        """A block of reads of one tick: the image as on entering it, whatever the device runs meanwhile
        (``ImageReader.pinned``); with ``tick``, that tick's image while the shared block still holds it, though
        the device has published newer ones (a hand-off run late samples the tick it is for)."""
        return self.reader.pinned(tick)

    @property
    def snapshot(self) -> TickImage:
        """The :class:`~valve_emulator.opcua.shared.TickImage` served now (inside :meth:`sampling`, the pinned one):
        a new object whenever anything was published, never changed, so what the server decodes from it may be kept
        as long as it is the one served (``OpcUaServer._column``)."""
        return self.reader.read()

    def computed_column(self, snapshot: TickImage, quantity: str) -> Any:
        """Every loop's double of ``quantity`` (one of ``shared.COMPUTED``) in ``snapshot`` (a :attr:`snapshot`
        taken before: the device may have published another since), or None."""
        row = self._rows.get(quantity)
        return None if row is None else snapshot.computed[row]

    def computed(self, index: int, quantity: str) -> float | None:
        if quantity == "time":
            return self.sample_time
        row = self._rows.get(quantity)
        return None if row is None else float(self.reader.read().computed[row, index])

    # --- notes from the device process -----------------------------------------------------------------

    def ticked(self, ticks: int, period: float) -> None:
        """The device ran ticks up to ``ticks``: wake whoever waits for them."""
        self._period = period
        ticks = self.ticks   # the image is published before the note: it is at least as new
        waiters = self._waiters
        while waiters and waiters[0][0] <= ticks:
            fut = heapq.heappop(waiters)[2]
            if not fut.done():
                fut.set_result(ticks)

    def alarmed(self, change: AlarmChange) -> None:
        self._alarms[change.index] = change
        for listener in list(self.alarm_listeners):
            listener(change)

    async def wait_for_tick(self, k: int) -> int:
        ticks = self.ticks
        if ticks >= k:
            return ticks
        fut = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiters, (k, next(self._seq), fut))
        return await fut

    # --- calls to the device process -------------------------------------------------------------------

    async def write(self, index: int, address: int, words: Sequence[int], role: Any) -> None:
        await self.channel.call("write", index, address, list(words), role)

    def raised_alarms(self) -> list[AlarmChange]:
        return [change for _, change in sorted(self._alarms.items()) if change.word]

    async def acknowledge_alarm(self, index: int) -> bool:
        return await self.channel.call("acknowledge_alarm", index)

    async def station_action(self, action: str, argument: Any = None) -> Any:
        return await self.channel.call("station_action", action, argument)

    @contextlib.asynccontextmanager
    async def paused(self) -> AsyncIterator[None]:
        """Nothing to do here: the device process pauses its device while this process builds."""
        yield

    def close(self) -> None:
        for _, _, fut in self._waiters:
            fut.cancel()
        self._waiters.clear()
        self.reader.close()


def child_main(fd: int) -> None:
    """The OPC UA process's entry point (``python -m valve_emulator.opcua FD``, started by
    :class:`~valve_emulator.opcua.process.OpcUaProcess`): read the :class:`ChildSpec` from the socket ``fd``,
    then serve until the device process closes it, and exit at once (nothing is left to tear down).

    Ctrl-C in a terminal and a service manager's SIGTERM reach the whole process group; this process leaves them
    to the device process, which stops it by closing the socket (a traceback here would only be noise, and an
    early exit would be reported as the OPC UA process failing)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    sock = socket.socket(fileno=fd)
    spec = read_first(sock)
    logging.basicConfig(level=spec.log_level,
                        format="%(asctime)s %(levelname)s [opcua process] %(name)s: %(message)s")
    asyncio.run(_serve(sock, spec))
    logging.shutdown()
    os._exit(0)


class ForwardLogs(logging.Handler):
    """Hand this process's log records to the device process (note ``log``), which logs them as its own: one
    log, in the format and at the place ``serve`` was told, whichever process the record comes from."""

    def __init__(self, channel: Channel) -> None:
        super().__init__()
        self.channel = channel
        self._thread = threading.get_ident()

    def emit(self, record: logging.LogRecord) -> None:
        if threading.get_ident() != self._thread:   # the channel belongs to the event loop's thread
            return
        try:
            exc_text = logging.Formatter().formatException(record.exc_info) if record.exc_info else None
            self.channel.note("log", record.name, record.levelno, record.getMessage(), exc_text)
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def _logging_to(channel: Channel) -> Iterator[None]:
    """Send every log record through ``channel`` inside the block (to stderr before and after it)."""
    root = logging.getLogger()
    local, forward = list(root.handlers), ForwardLogs(channel)
    for handler in local:
        root.removeHandler(handler)
    root.addHandler(forward)
    try:
        yield
    finally:
        root.removeHandler(forward)
        for handler in local:
            root.addHandler(handler)


async def _serve(sock: socket.socket, spec: ChildSpec) -> None:
    source = RemoteSource(spec)
    channel = Channel(sock, {"tick": source.ticked, "alarm": source.alarmed})
    source.channel = channel
    await channel.open()
    reading = asyncio.get_running_loop().create_task(channel.run())
    with _logging_to(channel):
        await _serve_on(channel, source, spec)
    await channel.close()
    reading.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await reading
    source.close()


async def _serve_on(channel: Channel, source: RemoteSource, spec: ChildSpec) -> None:
    from valve_emulator.opcua.server import PROCESS_PUBLISH_BUDGET, OpcUaServer

    server = OpcUaServer(source, loops=spec.loops, host=spec.host, port=spec.port, security=spec.security,
                         history=spec.history, history_path=spec.history_path,
                         publish_budget=PROCESS_PUBLISH_BUDGET, yield_while_sampling=False, hand_ahead=True)
    try:
        try:
            with _without_errors("asyncua.server.server"), _built_out_of_the_collectors_sight():
                await server.start()   # (an error: the device process says it in one line)
        except Exception as exc:   # a port in use, a certificate that does not load: the device process says so
            channel.note("failed", _sendable(exc))
            return
        channel.handlers["counters"] = server.counters
        channel.note("ready", server.port)
        await channel.closed.wait()
    finally:
        await server.stop()


#: The collector's thresholds in the OPC UA process once it serves (Python's default: 700, 10, 10). What a
#: notification makes (its DataValue, the item's queue entry) is freed by its reference count, not by the collector;
#: but with 700 the collector ran on the peaks of each hand-off (thousands of values in the items' queues until the
#: next publish), walked them and moved them to the older generations, whose collections then walked them again:
#: at 10 clients of 1,000 loops at 100 ms, 1,658 young, 151 middle and 14 full collections in 15 s (82 ms each), 15 % of
#: the process's CPU; with 20,000, 40 and 4 and none (docs/benchmarks.md §9.21).
SERVING_GC_THRESHOLDS = (20_000, 10, 10)


@contextlib.contextmanager
def _built_out_of_the_collectors_sight() -> Iterator[None]:
    """Build the address space with the garbage collector off, then move what was built out of its sight
    (:func:`gc.freeze`). A large address space is a few million objects that live as long as this process; each
    full collection walked them all: 0.1-1.3 s at 500 loops, twelve of them during the build and then one now
    and then while serving, each a stall of every session's requests and of the publisher (measured: another
    session's read p99 1.4 s). Serving, the collector runs at :data:`SERVING_GC_THRESHOLDS`."""
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        gc.set_threshold(*SERVING_GC_THRESHOLDS)
        gc.enable()


@contextlib.contextmanager
def _without_errors(logger: str) -> Iterator[None]:
    """Drop ``logger``'s ERROR records (with their tracebacks) inside the block."""
    def no_errors(record: logging.LogRecord) -> bool:
        return record.levelno < logging.ERROR

    log = logging.getLogger(logger)
    log.addFilter(no_errors)
    try:
        yield
    finally:
        log.removeFilter(no_errors)


def _sendable(exc: Exception) -> Exception:
    """``exc`` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc
