"""One Modbus TCP client connection: MBAP framing, fairness and self-defence (no pymodbus, no tasks).

:class:`ModbusConnection` is the ``asyncio.Protocol`` of the emulator's server. It cuts the byte stream into
MBAP frames (7-byte header: transaction id, protocol id 0, length 2..254, unit id) and hands every complete
frame to ``server.handle``, answering in order; pipelined requests are answered together in one write.

Defences, all driven by callbacks and timer handles, never by tasks:

- *Fairness.* At most :data:`FRAMES_PER_TURN` frames of one connection, and :data:`FRAMES_PER_ITERATION`
  of all connections together, are answered per event-loop iteration; the rest wait, with reading
  paused, for a later turn, taken in round-robin order (:class:`TurnBudget`). One client pipelining
  thousands of requests gets the same turns as everyone else, and however many clients pipeline, an
  iteration of the loop (and so the tick's lateness) stays within a couple of milliseconds.
- *Memory.* A client that does not read its answers stops being read (asyncio's write-buffer flow
  control), so its requests cannot pile up in our buffers; the guard's idle / frame deadlines end it. The
  kernel's socket buffers of each connection are capped at :data:`SOCKET_BUFFER`.
- *Error budget.* Exception answers cost a token each from a bucket of ``error_rate`` tokens refilled at
  ``error_rate`` per second (``device.error_rate``). A connection that runs out is read again only when
  the bucket is back above zero, so a client sending garbage in well-formed frames gets at most
  ``error_rate`` answers per second instead of the server's whole CPU; clients that make the occasional
  mistake never notice.
- *Tarpit.* A frame that is not Modbus TCP (protocol id not 0, length outside 2..254) cannot be
  resynchronised: the answers to the frames before it are sent, reading stops, and the connection is
  closed :data:`VIOLATION_DELAY` seconds later. A client that sends garbage and reconnects at once can then
  open at most one connection per ``VIOLATION_DELAY`` instead of thousands per second.
- *End of stream.* The frames received before a FIN are still answered; a partial frame left at the end
  can never complete, so the connection is then closed.

Communication faults (:mod:`~valve_emulator.device.comm`, asked per frame only while a unit has one): a
request that gets no response is consumed silently; ``close`` answers the frames before it and closes the
connection; a delay sends the answers before the delayed frame at once, holds everything after it (reading
paused, order kept) and sends its answer ``comm_delay_ms`` later.

Reading is paused whenever any of: the peer does not read (``pause_writing``), frames wait for their turn,
the error budget is exhausted, an answer is being delayed, or the connection is closing.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import socket
from typing import Any

from valve_emulator.device.registers import CommFault
from valve_emulator.device.roles import UNAUTHENTICATED, Role

__all__ = ["FRAMES_PER_ITERATION", "FRAMES_PER_TURN", "SOCKET_BUFFER", "VIOLATION_DELAY", "AdmittedConnection",
           "ModbusConnection", "TurnBudget"]

#: Frames answered per connection per event-loop iteration.
FRAMES_PER_TURN = 32
#: Frames answered by all connections together per event-loop iteration (a frame costs 5-20 µs).
FRAMES_PER_ITERATION = 128
#: Seconds between a protocol violation and the close (reading is stopped at once).
VIOLATION_DELAY = 1.0
#: Kernel receive and send buffer of each client socket, bytes (Linux doubles it for bookkeeping). A
#: Modbus request is at most 260 bytes and an answer 259, so this holds hundreds of pipelined requests;
#: it bounds the kernel memory a client that stops reading, or a tarpitted one, can make us hold.
SOCKET_BUFFER = 32 * 1024


class TurnBudget:
    """Round-robin scheduler for connections with more complete frames than one turn may answer.

    :attr:`left` frames may still be answered in the current event-loop iteration. A connection that has
    frames left over (or found the budget spent) queues itself with :meth:`wait`; once per iteration
    (a ``call_soon`` callback, armed by the first :meth:`spend` or :meth:`wait`) the budget is refilled
    and the queue served from the front, each waiting connection at most once, until the budget runs
    out. A connection still busy afterwards queues again at the back, so every waiting connection gets a
    turn in order, whoever sends the most.

    The refill is armed by a connection that waits and by a spend that leaves half the budget or less, not by
    every spend: iterations that serve a frame or two (the usual case) then cost one extra callback per
    ``frames / 2`` frames instead of one each. Still no iteration answers more than ``frames`` frames, and a
    connection waits only in an iteration that has answered at least half of them.
    """

    def __init__(self, frames: int = FRAMES_PER_ITERATION) -> None:
        self.frames = self.left = int(frames)
        self.waiting: collections.deque = collections.deque()
        self._armed = False

    def spend(self, n: int) -> None:
        self.left -= n
        if self.left <= self.frames // 2:
            self._arm()   # refilled at the next iteration, long before it runs out in the usual case

    def wait(self, conn: ModbusConnection) -> None:
        self.waiting.append(conn)
        self._arm()

    def _arm(self) -> None:
        if not self._armed:
            self._armed = True
            asyncio.get_running_loop().call_soon(self._run)

    def _run(self) -> None:
        self._armed = False
        self.left = self.frames
        for _ in range(len(self.waiting)):
            if self.left <= 0:
                self._arm()  # the rest keep their place for the next iteration
                break
            self.waiting.popleft()._serve()


class AdmittedConnection(asyncio.Protocol):
    """What every client connection of the TCP port does, whatever it speaks (Modbus TCP, TLS, RTU frames):
    admission by the server's guard (:class:`~valve_emulator.device.guard.ConnectionGuard`), its role, its
    place in the server's ``connection_set``, and its slot given back when it goes.

    ``server`` (set by the subclass's ``__init__``) provides ``guard``, ``plain_role(ip)`` and the set
    ``connection_set``.
    """

    server: Any
    transport: asyncio.Transport
    peer_ip: str = ""
    role: Role = UNAUTHENTICATED
    slot: Any = None

    def _admit(self, transport: asyncio.BaseTransport) -> bool:
        """Take the transport and ask the guard for a slot for its peer; refused (at the connection limit), the
        transport is aborted and False returned."""
        self.transport = transport  # type: ignore[assignment]
        peer = transport.get_extra_info("peername")
        self.peer_ip = peer[0] if peer else ""
        self.slot = self.server.guard.admit(f"{peer[0]}:{peer[1]}" if peer else "?", transport.abort)
        if self.slot is None:
            transport.abort()
            return False
        return True

    def _enter(self) -> None:
        """The admitted client's role, and its place among the server's connections."""
        self.role = self.permission()
        self.server.connection_set.add(self)

    def permission(self) -> Role:
        """This client's role (asked again when the server is reconfigured): the plain port's rule."""
        return self.server.plain_role(self.peer_ip)

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.connection_set.discard(self)
        self.server.guard.release(self.slot)


class ModbusConnection(AdmittedConnection):
    """One client of ``server``.

    ``server`` provides ``guard`` (:class:`~valve_emulator.device.guard.ConnectionGuard`), ``turns``
    (:class:`TurnBudget`), ``handle(frame, role, peer=...) -> bytes``, ``plain_role(ip)``, the
    set ``connection_set`` and the counters ``exceptions``, ``violations``, ``throttled``.
    """

    def __init__(self, server: Any) -> None:
        self.server = server
        self.transport: asyncio.Transport
        self.peer_ip = ""
        #: what this client may write (:class:`~valve_emulator.device.roles.Role`)
        self.role = UNAUTHENTICATED
        #: the client as the log names it: its address (and, over TLS, its certificate and role)
        self.who = ""
        self.slot = None
        self._buf = bytearray()
        self._write_paused = False
        self._backlog = False
        self._scheduled = False
        self._closing = False
        self._eof = False
        self._throttle: asyncio.TimerHandle | None = None
        self._close_timer: asyncio.TimerHandle | None = None
        self._delayed: asyncio.TimerHandle | None = None
        self._tokens = 0.0
        self._stamp = 0.0

    # --- asyncio.Protocol -----------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if not self._admit(transport):
            return
        guard = self.server.guard
        self._tokens, self._stamp = float(guard.error_rate), guard.clock()
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
                    sock.setsockopt(socket.SOL_SOCKET, option, SOCKET_BUFFER)
            except OSError:  # not every transport (or platform) allows it; the defaults then apply
                pass
        self.who = self.peer_ip
        self._enter()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        self._buf.clear()
        for timer in (self._throttle, self._close_timer, self._delayed):
            if timer is not None:
                timer.cancel()

    def pause_writing(self) -> None:
        self._write_paused = True
        self._sync_reading()

    def resume_writing(self) -> None:
        self._write_paused = False
        self._schedule()
        self._sync_reading()

    def data_received(self, data: bytes) -> None:
        if self.slot is None or self._closing:
            return
        if not self._buf and not self._backlog and self._delayed is None and self._alone(data):
            return
        self._buf += data
        if not self._backlog:
            self._serve()

    def _alone(self, frame: bytes) -> bool:
        """Answer ``frame`` when it is exactly one complete Modbus TCP frame that arrived on its own (what a
        client with one request outstanding sends) and nothing holds this connection back: what :meth:`_serve`
        would do, without copying it through the buffer. False: the general path must serve it."""
        server = self.server
        turns, n = server.turns, len(frame)
        if (n < 8 or frame[2] or frame[3] or n != 6 + ((frame[4] << 8) | frame[5]) or n > 260 or turns.left <= 0
                or server.comm.active or self.transport.is_closing()):
            return False
        errors0 = server.exceptions
        self._sent(1, server.handle(frame, self.role, peer=self.who, client=self.slot.peer), errors0,
                   partial=False)
        if server.exceptions != errors0:
            self._sync_reading()   # the error budget may have run out
        return True

    def _sent(self, frames: int, data: bytes, errors0: int, *, partial: bool) -> None:
        """Send ``data``, the answers to ``frames`` frames just served, and book them: the turn budget, the slot's
        deadlines (``partial``: a partial frame is left in the buffer, its deadline runs from now) and the error
        budget for the exception answers among them (``server.exceptions`` was ``errors0`` before them)."""
        server, slot = self.server, self.slot
        server.turns.spend(frames)
        slot.last_request = now = server.guard.clock()
        slot.partial_since = now if partial else None
        self.transport.write(data)
        if server.exceptions != errors0:
            self._spend(server.exceptions - errors0, now)

    def eof_received(self) -> bool:
        self._eof = True
        if not self._backlog and self._delayed is None:
            self._close_now()
        return True   # we close the transport ourselves, after answering the frames still queued

    # --- serving --------------------------------------------------------------------------------------

    def _serve(self) -> None:
        self._scheduled = False
        transport, slot, server = self.transport, self.slot, self.server
        if slot is None or self._closing or transport.is_closing() or self._delayed is not None:
            return
        buf, errors0, turns, comm = self._buf, server.exceptions, server.turns, server.comm
        end_of_data, pos, answers, frames = len(buf), 0, [], 0
        limit = min(FRAMES_PER_TURN, turns.left)
        while end_of_data - pos >= 7 and frames < limit:
            length = (buf[pos + 4] << 8) | buf[pos + 5]
            if buf[pos + 2] or buf[pos + 3] or not 2 <= length <= 254:
                turns.spend(frames)
                self._violation(bytes(buf[pos:pos + 7]), answers)
                return
            end = pos + 6 + length
            if end > end_of_data:
                break  # partial frame: wait for the rest
            frame = bytes(buf[pos:end])
            pos, frames = end, frames + 1
            state = comm.plan(frame[6], frame[7:]) if comm.active else None
            if state is None:
                answers.append(server.handle(frame, self.role, peer=self.who, client=slot.peer))
                continue
            answer = server.handle_faulted(frame, self.role, state, peer=self.who, client=slot.peer)
            if state.fault is CommFault.CLOSE:
                turns.spend(frames)
                if answers:
                    transport.write(b"".join(answers))
                self._close_now()
                return
            if state.delay_ms and answer is not None:
                self._delayed = asyncio.get_running_loop().call_later(state.delay_ms / 1000, self._release,
                                                                       answer)
                break
            if answer is not None:
                answers.append(answer)
        del buf[:pos]
        if frames:
            self._sent(frames, b"".join(answers), errors0, partial=bool(buf))
        elif buf and slot.partial_since is None:
            slot.partial_since = server.guard.clock()
        self._backlog = frames == limit and _complete(buf) and self._delayed is None
        if self._backlog:
            self._schedule()
        elif self._eof and self._delayed is None:
            self._close_now()
        self._sync_reading()

    def _release(self, answer: bytes) -> None:
        """The delay of a delayed answer is over: send it and serve what arrived meanwhile."""
        self._delayed = None
        if self._closing or self.transport.is_closing():
            return
        self.transport.write(answer)
        self._serve()

    def _schedule(self) -> None:
        """Queue for a turn to serve the waiting frames, unless something holds this connection back."""
        if (self._backlog and not self._scheduled and not self._write_paused and self._throttle is None
                and not self._closing):
            self._scheduled = True
            self.server.turns.wait(self)

    def _sync_reading(self) -> None:
        transport = self.transport
        if transport.is_closing():
            return
        hold = (self._write_paused or self._backlog or self._throttle is not None or self._closing
                or self._delayed is not None)
        if hold and transport.is_reading():
            transport.pause_reading()
        elif not hold and not transport.is_reading():
            transport.resume_reading()

    # --- defences -------------------------------------------------------------------------------------

    def _spend(self, errors: int, now: float) -> None:
        """Take ``errors`` tokens from the error budget; out of tokens: stop reading until it refills."""
        guard = self.server.guard
        rate = guard.error_rate
        self._tokens = min(float(rate), self._tokens + (now - self._stamp) * rate) - errors
        self._stamp = now
        if self._tokens < 0 and self._throttle is None:
            self.server.throttled += 1
            guard.limiter.log("throttled", logging.INFO, "slowing down connection from %s: more than %g "
                              "exception answers per second (device.error_rate)", self.slot.peer, rate)
            self._throttle = asyncio.get_running_loop().call_later(-self._tokens / rate, self._unthrottle)

    def _unthrottle(self) -> None:
        self._throttle = None
        self._schedule()
        self._sync_reading()

    def _violation(self, header: bytes, answers: list[bytes]) -> None:
        """Not a Modbus TCP frame: answer what came before it, stop reading, close a little later."""
        server = self.server
        server.violations += 1
        server.guard.limiter.log("not modbus", logging.WARNING,
                                 "closing connection from %s: not a Modbus TCP frame (header %s)",
                                 self.slot.peer, header.hex())
        self._buf.clear()
        if answers:
            self.transport.write(b"".join(answers))
        self._closing = True
        self._mark_closing()
        self._sync_reading()
        self._close_timer = asyncio.get_running_loop().call_later(VIOLATION_DELAY, self.transport.close)

    def _close_now(self) -> None:
        self._closing = True
        self._buf.clear()  # a partial frame at the end of the stream can never complete
        self._mark_closing()
        self.transport.close()

    def _mark_closing(self) -> None:
        if self.slot is not None:
            self.server.guard.closing(self.slot)


def _complete(buf: bytearray) -> bool:
    """Does ``buf`` start with a complete frame, or with a header the next turn will reject at once?"""
    if len(buf) < 7:
        return False
    length = (buf[4] << 8) | buf[5]
    return bool(buf[2] or buf[3]) or not 2 <= length <= 254 or len(buf) >= 6 + length
