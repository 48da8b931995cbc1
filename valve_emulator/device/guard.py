"""Connection hygiene for the Modbus TCP server: admission, deadlines and logs that a flood cannot inflate.

Pure asyncio callbacks (no pymodbus, no tasks): the server asks :class:`ConnectionGuard` for a
:class:`Slot` when a client connects and gives it back when the connection is lost. One timer (a
``loop.call_later`` chain, not a task, so it never shows in the task count) sweeps the slots every
``min(idle_timeout, frame_timeout) / 4`` seconds (clamped to 10 ms .. 1 s) and aborts

- an *idle* connection: no complete request for ``idle_timeout`` s. This also clears *half-open*
  connections (the peer vanished without a FIN, so nothing arrives any more) and clients that stopped
  reading our answers (the server then stops reading them, so no request completes);
- a *slow* connection: a request frame started more than ``frame_timeout`` s ago is still incomplete. A
  client sending one byte a second therefore loses its connection after ``frame_timeout`` whatever it does;
- a connection that has been *closing* for ``frame_timeout`` s (answers it never reads keep a graceful
  close from completing).

A connection beyond ``max_connections`` is refused (closed at once). A connection the server is closing
(see :meth:`ConnectionGuard.closing`) no longer counts against that limit: a client that sends garbage,
hangs up and reconnects at once must not fill the table with connections that are on their way out.
At most ``max_connections`` of those are kept; beyond that the oldest is aborted. Every deadline is
enforced to within one sweep interval.

Hostile traffic could otherwise turn the log into the bottleneck, so repeated messages of one kind go
through :class:`LogLimiter` (one line per kind per interval, the number suppressed reported on the next
line), and :class:`RefusalLog` logs a refused write or handshake once per client and cause per interval.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import math
import time
from collections.abc import Callable
from typing import Any

__all__ = ["ConnectionGuard", "LogLimiter", "RefusalLog", "Slot", "binds_all_interfaces", "is_loopback"]

_log = logging.getLogger("valve_emulator.device.server")  # one logger for everything about connections


def is_loopback(host: str) -> bool:
    """``True`` for ``localhost`` and loopback addresses (127.0.0.0/8, ::1): where a server may listen without
    authentication (the station without a token, OPC UA with policy None)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def binds_all_interfaces(host: str | None) -> bool:
    """Does listening on ``host`` accept connections on every interface (``0.0.0.0``, ``::``, ``""``)?"""
    if host is None or host in ("", "*"):
        return True
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False


class LogLimiter:
    """At most one log line per ``key`` every ``interval`` seconds; the rest are counted, not lost.

    The next line logged for a key says how many were suppressed since the previous one, and
    :meth:`flush` (called by the guard's sweep) reports a pending count once the interval has passed even
    when no new message of that kind comes.
    """

    def __init__(self, logger: logging.Logger = _log, *, interval: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.logger, self.interval, self._clock = logger, float(interval), clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, tuple[int, int, str]] = {}   # key -> (count, level, what)

    def log(self, key: str, level: int, msg: str, *args: Any) -> bool:
        """Log ``msg % args`` unless a line of this ``key`` was logged less than ``interval`` ago."""
        now = self._clock()
        if now - self._last.get(key, -math.inf) < self.interval:
            count, _, _ = self._suppressed.get(key, (0, level, key))
            self._suppressed[key] = (count + 1, level, key)
            return False
        self._last[key] = now
        count = self._suppressed.pop(key, (0, level, key))[0]
        if count:
            msg += " (%d more like this in the last %.0f s were not logged)"
            args = (*args, count, self.interval)
        self.logger.log(level, msg, *args)
        return True

    def flush(self) -> None:
        """Report suppressed counts whose interval is over."""
        now = self._clock()
        for key, (count, level, _) in list(self._suppressed.items()):
            if now - self._last.get(key, -math.inf) >= self.interval:
                del self._suppressed[key]
                self._last[key] = now
                self.logger.log(level, "%d more '%s' events in the last %.0f s were not logged",
                                count, key, self.interval)


class RefusalLog:
    """Log refused requests -- writes a role may not make, handshakes of certificates without a known role --
    once per (client, cause) per ``interval`` seconds, so a flood cannot fill the disk.

    ``client`` is the client as the log should name it (its address; over TLS also the certificate subject
    and role), ``cause`` anything hashable that says why (register and exception code; the handshake's
    reason). The first refusal of a pair is logged at WARNING; the repeats within ``interval`` are counted,
    and the pair's next line, once the interval is over, says how many were not logged. A flood of N
    refusals over T seconds thus writes about ``T / interval`` lines, whatever N is.

    ``capacity`` bounds the pairs remembered (a client cycling through causes or addresses): when it is
    reached, pairs whose interval is over are forgotten; if that frees nothing, one line says so and the
    new pairs are logged at DEBUG only until it does.
    """

    def __init__(self, logger: logging.Logger = _log, *, interval: float = 10.0, capacity: int = 10_000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.logger, self.interval, self.capacity, self._clock = logger, float(interval), int(capacity), clock
        self._last: dict[tuple[str, Any], float] = {}     # (client, cause) -> when its last line was logged
        self._suppressed: dict[tuple[str, Any], int] = {}
        self._full_since: float | None = None
        #: refusals noted (logged or not)
        self.refused = 0

    def note(self, client: str, cause: Any, msg: str, *args: Any) -> bool:
        """Count a refusal; log ``msg % args`` at WARNING unless this (client, cause) was logged less than
        ``interval`` ago. Returns whether a line was logged at WARNING."""
        self.refused += 1
        now, key = self._clock(), (client, cause)
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        if last is None and len(self._last) >= self.capacity and not self._forget(now):
            if self._full_since is None or now - self._full_since >= self.interval:
                self._full_since = now
                self.logger.warning("refusal log holds %d (client, cause) pairs; new ones are logged at DEBUG "
                                    "only for now", self.capacity)
            self.logger.debug(msg, *args)
            return False
        self._last[key] = now
        missed = self._suppressed.pop(key, 0)
        tail = f"; {missed} more like this in the last {self.interval:g} s were not logged" if missed else ""
        self.logger.warning(msg + "%s; repeats from this client are logged at most once every %g s",
                            *args, tail, self.interval)
        return True

    def _forget(self, now: float) -> bool:
        """Drop the pairs whose interval is over; did that free room?"""
        for key in [k for k, t in self._last.items() if now - t >= self.interval]:
            del self._last[key]
            self._suppressed.pop(key, None)
        return len(self._last) < self.capacity

    def clear(self) -> None:
        self._last.clear()
        self._suppressed.clear()


class Slot:
    """One admitted connection's timestamps (monotonic seconds), updated by the connection itself.

    ``last_request``: when the last complete request arrived (or the connection was made).
    ``partial_since``: when the incomplete frame now in the buffer began, ``None`` when there is none.
    ``closing_since``: when the server started closing it (:meth:`ConnectionGuard.closing`), ``None`` while
    open.
    """

    __slots__ = ("peer", "abort", "last_request", "partial_since", "closing_since")

    def __init__(self, peer: str, abort: Callable[[], None], now: float) -> None:
        self.peer, self.abort = peer, abort
        self.last_request = now
        self.partial_since: float | None = None
        self.closing_since: float | None = None


class ConnectionGuard:
    """Admission control and deadlines for the connections of one server.

    Parameters
    ----------
    max_connections : simultaneous connections admitted (>= 1).
    idle_timeout, frame_timeout : seconds (> 0), see the module docstring.
    error_rate : exception answers per second per connection, kept here for the connections (> 0).
    clock : monotonic clock (injectable for tests; the server uses the real one).

    Counters: ``refused`` (connections refused at the limit), ``expired`` (aborted per deadline kind).
    """

    def __init__(self, *, max_connections: int = 64, idle_timeout: float = 60.0, frame_timeout: float = 5.0,
                 error_rate: float = 100.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.slots: dict[int, Slot] = {}      # open connections, counted against max_connections
        self.leaving: dict[int, Slot] = {}    # connections being closed, oldest first
        self.refused = 0
        self.expired = {"idle": 0, "slow": 0, "closing": 0}
        self.limiter = LogLimiter(clock=clock)
        self._timer: asyncio.TimerHandle | None = None
        self.configure(max_connections=max_connections, idle_timeout=idle_timeout, frame_timeout=frame_timeout,
                       error_rate=error_rate)

    def configure(self, *, max_connections: int, idle_timeout: float, frame_timeout: float,
                  error_rate: float) -> None:
        """Change the limits; open connections over a lower limit stay (they are not dropped).

        ``error_rate`` (exception answers per second per connection) is read by the connections' error
        budget (:mod:`~valve_emulator.device.connection`); the guard only keeps it with the other limits.
        """
        if not (isinstance(max_connections, int) and max_connections >= 1):
            raise ValueError(f"max_connections must be an integer >= 1, got {max_connections!r}")
        for name, value in (("idle_timeout", idle_timeout), ("frame_timeout", frame_timeout),
                            ("error_rate", error_rate)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        self.max_connections = max_connections
        self.idle_timeout, self.frame_timeout = float(idle_timeout), float(frame_timeout)
        self.error_rate = float(error_rate)
        self.interval = min(1.0, max(0.01, min(idle_timeout, frame_timeout) / 4))

    @property
    def open(self) -> int:
        return len(self.slots)

    # --- admission ---------------------------------------------------------------------------------

    def admit(self, peer: str, abort: Callable[[], None]) -> Slot | None:
        """A :class:`Slot` for a new connection from ``peer``, or ``None`` (refused, logged) when full."""
        if len(self.slots) >= self.max_connections:
            self.refused += 1
            self.limiter.log("refused connection", logging.WARNING,
                             "refused connection from %s: %d connections already open "
                             "(device.max_connections = %d)", peer, len(self.slots), self.max_connections)
            return None
        slot = Slot(peer, abort, self.clock())
        self.slots[id(slot)] = slot
        return slot

    def release(self, slot: Slot | None) -> None:
        """The connection is gone: forget its slot."""
        if slot is not None:
            self.slots.pop(id(slot), None)
            self.leaving.pop(id(slot), None)

    def closing(self, slot: Slot) -> None:
        """The server has started closing ``slot``'s connection: free its place, keep its deadline."""
        if slot.closing_since is not None:
            return
        slot.closing_since = self.clock()
        if self.slots.pop(id(slot), None) is None:
            return  # already released
        self.leaving[id(slot)] = slot
        while len(self.leaving) > self.max_connections:
            oldest = self.leaving.pop(next(iter(self.leaving)))
            self.expired["closing"] += 1
            oldest.abort()

    # --- deadlines ---------------------------------------------------------------------------------

    def sweep(self) -> int:
        """Abort every connection past a deadline now; returns how many."""
        now, idle, frame = self.clock(), self.idle_timeout, self.frame_timeout
        late = [(slot, "closing") for slot in self.leaving.values() if now - slot.closing_since > frame]
        for slot in self.slots.values():
            if slot.partial_since is not None and now - slot.partial_since > frame:
                late.append((slot, "slow"))
            elif now - slot.last_request > idle:
                late.append((slot, "idle"))
        for slot, why in late:
            self.expired[why] += 1
            self.release(slot)  # the slot is free now, whenever the transport reports the loss
            what = {"idle": f"no complete request for {idle:g} s (device.idle_timeout)",
                    "slow": f"request frame incomplete after {frame:g} s (device.frame_timeout)",
                    "closing": f"close not completed after {frame:g} s"}[why]
            self.limiter.log(f"timeout {why}", logging.INFO, "closing connection from %s: %s", slot.peer, what)
            slot.abort()
        self.limiter.flush()
        return len(late)

    def start(self) -> None:
        """Begin sweeping on the running loop (idempotent)."""
        if self._timer is None:
            self._schedule(asyncio.get_running_loop())

    def stop(self) -> None:
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()

    def _schedule(self, loop: asyncio.AbstractEventLoop) -> None:
        self._timer = loop.call_later(self.interval, self._run, loop)

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            self.sweep()
        except Exception:  # a bug here must not end the sweeping (and with it every deadline)
            _log.exception("connection sweep failed")
        if self._timer is not None:
            self._schedule(loop)
