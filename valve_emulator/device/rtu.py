"""Modbus RTU: the same server on a serial line, and RTU frames over TCP ("RTU over TCP", encapsulated).

*MODBUS over Serial Line Specification and Implementation Guide V1.02*:

- A frame is ``address | PDU | CRC`` with the CRC-16 of §6.2.2 (polynomial 0xA001 reflected, initial
  0xFFFF), low byte first (:func:`crc16`). Over the whole frame, CRC included, the CRC is 0.
- A character is 11 bits: start, 8 data, parity, stop; without parity, two stop bits (§2.5.1). The
  default is 19200 baud, even parity (8E1). ``--stopbits`` lets 8N1 / 8E2 lines be served as well.
- Frames are delimited by silence (§2.5.1.1): at least 3.5 character times between frames; a silence of
  more than 1.5 character times inside a frame makes it incomplete, and it is discarded. Above 19200 baud
  the timers are fixed at 1.75 ms and 0.75 ms (:class:`SerialSettings`). A request whose length follows
  from its function code (:func:`request_length`) and whose CRC checks is answered as soon as its last byte
  is in, as libmodbus and most devices do; any other frame ends with the t3.5 silence. (Waiting for the
  silence would add t3.5 to every answer: at 115200 baud that alone costs a third of the line's rate.)
- A frame with a bad CRC is discarded without a reply (§2.5.1.2), and counted (FC8 sub-function 0x0C).
  So is a frame longer than 256 bytes, the longest the specification allows (§2.5.1): the serial link keeps
  at most that much of it, however long the line chatters without a silence.
  A frame for an address not served here is not answered (another slave on the bus may own it).
- Address 0 is broadcast (§2.1): a write is carried out by every unit served here, and nobody answers;
  a broadcast read is ignored.

:class:`RtuSerialLink` serves a serial device (a real RS-485 adapter or one end of a ``socat`` pty pair),
configured through pyserial and read through the event loop, so TCP and RTU run in one process on one
tick. :class:`RtuStreamConnection` is the ``asyncio.Protocol`` of ``--framer rtu``: RTU frames with CRC and
no MBAP header on a TCP stream, where there is no silence to go by: a frame's length follows from its
function code (and byte count), or else from the first length whose CRC checks.

Both answer through :class:`RtuResponder`, which also applies communication faults
(:mod:`~valve_emulator.device.comm`): ``bad_crc`` sends the answer with its CRC inverted.
"""

from __future__ import annotations

import asyncio
import logging
import os
from dataclasses import dataclass
from typing import Any, Final

from valve_emulator.device.connection import AdmittedConnection
from valve_emulator.device.pdu import BIT_WRITE_FUNCTIONS, WRITE_FUNCTIONS
from valve_emulator.device.registers import CommFault
from valve_emulator.device.roles import UNAUTHENTICATED, Role
from valve_emulator.errors import UserError

__all__ = ["PARITIES", "STREAM_GAP", "RtuResponder", "RtuSerialLink", "RtuStreamConnection", "SerialSettings", "crc16",
           "request_length", "with_crc"]

_log = logging.getLogger("valve_emulator.device.server")

PARITIES: Final = ("E", "O", "N")
_BROADCAST_WRITES: Final = WRITE_FUNCTIONS | BIT_WRITE_FUNCTIONS


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE: Final = _crc_table()


def crc16(data: bytes) -> int:
    """The Modbus CRC-16 of ``data`` (transmitted low byte first)."""
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ _TABLE[(crc ^ byte) & 0xFF]
    return crc


def with_crc(frame: bytes) -> bytes:
    """``frame`` followed by its CRC, low byte first."""
    return frame + crc16(frame).to_bytes(2, "little")


@dataclass(frozen=True, slots=True, kw_only=True)
class SerialSettings:
    """A serial line: ``baud``, ``parity`` (``E``, ``O``, ``N``), ``stopbits`` (1, 2), 8 data bits."""

    baud: int = 19200
    parity: str = "E"
    stopbits: int = 1

    def __post_init__(self) -> None:
        if not (isinstance(self.baud, int) and 300 <= self.baud <= 4_000_000):
            raise UserError(f"baud must be an integer 300..4000000, got {self.baud!r}")
        if self.parity not in PARITIES:
            raise UserError(f"parity must be one of {', '.join(PARITIES)}, got {self.parity!r}")
        if self.stopbits not in (1, 2):
            raise UserError(f"stopbits must be 1 or 2, got {self.stopbits!r}")

    @property
    def bits_per_char(self) -> int:
        """Start + 8 data + parity + stop bits (11 for 8E1, 8N2, 8O1; 10 for 8N1)."""
        return 1 + 8 + (self.parity != "N") + self.stopbits

    @property
    def char_time(self) -> float:
        return self.bits_per_char / self.baud

    @property
    def t35(self) -> float:
        """Silence that ends a frame, s (§2.5.1.1; fixed 1.75 ms above 19200 baud)."""
        return 3.5 * self.char_time if self.baud <= 19200 else 1.75e-3

    @property
    def t15(self) -> float:
        """Longest silence allowed inside a frame, s (fixed 0.75 ms above 19200 baud)."""
        return 1.5 * self.char_time if self.baud <= 19200 else 0.75e-3

    def __str__(self) -> str:
        return f"{self.baud} 8{self.parity}{self.stopbits}"


class RtuResponder:
    """Answers complete RTU frames for ``server`` (an :class:`~valve_emulator.device.server.EmulatorServer`).

    ``silent_unknown``: a unit not served here gets no answer (a serial bus) instead of exception 0x0B
    (RTU over TCP, where the client has nobody else to hear from).
    """

    def __init__(self, server: Any, *, silent_unknown: bool) -> None:
        self.server = server
        self.silent_unknown = silent_unknown

    def respond(self, frame: bytes, role: Role) -> tuple[bytes | None, float, CommFault]:
        """``(response frame or None, delay in s, communication fault applied)`` for one received ``frame``
        (address, PDU, CRC)."""
        server = self.server
        if len(frame) < 4 or crc16(frame) != 0:
            server.crc_errors += 1
            return None, 0.0, CommFault.NONE
        unit, pdu = frame[0], frame[1:-2]
        if unit == 0:
            if pdu[0] in _BROADCAST_WRITES:
                server.broadcast(pdu, role)
            return None, 0.0, CommFault.NONE
        if unit not in server.device.layout.regions and self.silent_unknown:
            server.foreign_frames += 1
            return None, 0.0, CommFault.NONE
        state = server.comm.plan(unit, pdu) if server.comm.active else None
        if state is None:
            reply = server.answer(unit, pdu, role)
        else:
            reply = server.answer_faulted(unit, pdu, role, state)
            if reply is None:
                return None, 0.0, state.fault
        out = bytes((unit,)) + reply
        crc = crc16(out)
        if state is not None and state.fault is CommFault.BAD_CRC:
            crc ^= 0xFFFF
        if state is None:
            return out + crc.to_bytes(2, "little"), 0.0, CommFault.NONE
        return out + crc.to_bytes(2, "little"), state.delay_ms / 1000, state.fault


class RtuSerialLink:
    """Serves ``server``'s units on the serial device ``port`` with ``settings`` (silence-delimited frames).

    :meth:`open` configures the line through pyserial and reads it from the running event loop; :meth:`close`
    stops. Counters: ``frames`` (complete frames seen), ``dropped`` (frames discarded for a gap inside).
    """

    def __init__(self, server: Any, port: str, settings: SerialSettings = SerialSettings()) -> None:
        self.server, self.port, self.settings = server, port, settings
        self.responder = RtuResponder(server, silent_unknown=True)
        self.frames = self.dropped = 0
        self._serial: Any = None
        self._fd = -1
        self._buf = bytearray()
        self._last = 0.0
        self._broken = False
        self._timer: asyncio.TimerHandle | None = None
        self._pending: set[asyncio.TimerHandle] = set()
        self._loop: asyncio.AbstractEventLoop | None = None

    def open(self) -> None:
        """Open and configure the line (``OSError`` / ``ValueError`` naming the device if it cannot)."""
        import serial  # pyserial: termios settings of the line, portable

        parity = {"E": serial.PARITY_EVEN, "O": serial.PARITY_ODD, "N": serial.PARITY_NONE}[self.settings.parity]
        try:
            self._serial = serial.Serial(self.port, baudrate=self.settings.baud, parity=parity,
                                         stopbits=self.settings.stopbits, bytesize=8, timeout=0)
        except (serial.SerialException, ValueError) as exc:
            raise OSError(f"serial device {self.port}: {exc}") from None
        self._fd = self._serial.fileno()
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self._fd, self._readable)
        _log.info("serving units %s on %s (%s, Modbus RTU)", list(self.server.units), self.port, self.settings)

    def close(self) -> None:
        if self._loop is not None and self._fd >= 0:
            self._loop.remove_reader(self._fd)
        for timer in (self._timer, *self._pending):
            if timer is not None:
                timer.cancel()
        self._pending.clear()
        if self._serial is not None:
            self._serial.close()
        self._serial, self._fd, self._loop = None, -1, None

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:   # the other end of a pty went away: keep listening for a new one
            _log.debug("serial %s: %s", self.port, exc)
            data = b""
        if not data:
            return
        now = self._loop.time()
        if self._timer is not None and now - self._last >= self.settings.t35:
            # the end-of-frame timer is due but the loop ran this reader first (a busy loop): the silence
            # has passed, so the frame before it ends here, and these bytes start the next one
            self._timer.cancel()
            self._end_of_frame()
        if self._buf and now - self._last > self.settings.t15:
            self._broken = True   # a silence inside the frame: it is discarded when it ends (§2.5.1.1)
        if len(self._buf) + len(data) > _MAX_FRAME:
            # longer than any RTU frame (256 bytes, §2.5.1): noise, discarded when the silence comes. Only
            # the tail is kept, so a line that never falls silent cannot make the buffer grow.
            self._broken = True
            self._buf.clear()
            data = data[-_MAX_FRAME:]
        self._buf += data
        self._last = now
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        n = request_length(self._buf)
        if n is not None and len(self._buf) == n and not self._broken and crc16(self._buf) == 0:
            self._end_of_frame()   # complete by its length and CRC: no need to wait for the silence
            return
        self._timer = self._loop.call_later(self.settings.t35, self._end_of_frame)

    def _end_of_frame(self) -> None:
        self._timer = None
        frame, broken = bytes(self._buf), self._broken
        self._buf.clear()
        self._broken = False
        self.frames += 1
        if broken:
            self.dropped += 1
            self.server.crc_errors += 1
            return
        reply, delay, _ = self.responder.respond(frame, self.server.plain_role(""))
        if reply is None:
            return
        if delay > 0:
            handle = self._loop.call_later(delay, self._send_later, reply)
            self._pending.add(handle)
        else:
            self._send(reply)

    def _send_later(self, reply: bytes) -> None:
        self._pending = {h for h in self._pending if not h.cancelled() and h.when() > self._loop.time()}
        self._send(reply)

    def _send(self, reply: bytes) -> None:
        if self._fd >= 0:
            try:
                os.write(self._fd, reply)
            except OSError as exc:
                _log.debug("serial %s: write failed: %s", self.port, exc)


def request_length(buf: bytes | bytearray) -> int | None:
    """Length of the RTU request frame at the start of ``buf`` when its function code tells it (``None``:
    not yet known, or a function code whose length is only found by its CRC)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6, 8):
        return 8
    if fc == 22:
        return 10
    if fc == 43:
        return 7
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else None
    if fc == 23:
        return 13 + buf[10] if len(buf) >= 11 else None
    return None


_MAX_FRAME: Final = 256
#: Seconds of silence after which an incomplete RTU-over-TCP frame is abandoned.
STREAM_GAP: Final = 0.05


class RtuStreamConnection(AdmittedConnection):
    """One client of ``--framer rtu``: RTU frames (address, PDU, CRC) on a TCP stream.

    A frame whose CRC does not check is dropped with everything received so far (as a serial device drops
    a frame); bytes left over that no frame explains are dropped when nothing has arrived for
    :data:`STREAM_GAP` seconds, the stream's stand-in for the serial line's silence, so the next request
    is read from its first byte again. Admission and the idle deadline are the Modbus TCP server's
    (:class:`~valve_emulator.device.guard.ConnectionGuard`).
    """

    def __init__(self, server: Any) -> None:
        self.server = server
        self.responder = RtuResponder(server, silent_unknown=False)
        self.transport: asyncio.Transport
        self.slot = None
        self.role = UNAUTHENTICATED
        self.peer_ip = ""
        self._buf = bytearray()
        self._last = 0.0
        self._pending: set[asyncio.TimerHandle] = set()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if self._admit(transport):
            self._enter()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        for handle in self._pending:
            handle.cancel()

    def data_received(self, data: bytes) -> None:
        if self.slot is None:
            return
        buf = self._buf
        now = self.server.guard.clock()
        if buf and now - self._last > STREAM_GAP:
            self._drop()   # a stale partial frame: the new data starts a request
        self._last = now
        buf += data
        while len(buf) >= 4:
            n = request_length(buf) or _crc_length(buf)
            if n is None:
                if len(buf) >= _MAX_FRAME:
                    self._drop()
                break
            if len(buf) < n:
                break
            frame = bytes(buf[:n])
            if crc16(frame) != 0:
                self._drop()
                break
            del buf[:n]
            self.slot.last_request = now
            reply, delay, fault = self.responder.respond(frame, self.role)
            if fault is CommFault.CLOSE:
                self._buf.clear()
                self.transport.close()
                return
            if reply is None:
                continue
            if delay > 0:
                handle = asyncio.get_running_loop().call_later(delay, self._write, reply)
                self._pending.add(handle)
            else:
                self._write(reply)
        self.slot.partial_since = now if buf else None

    def _drop(self) -> None:
        self.server.crc_errors += 1
        self._buf.clear()

    def _write(self, reply: bytes) -> None:
        if not self.transport.is_closing():
            self.transport.write(reply)


def _crc_length(buf: bytes | bytearray) -> int | None:
    """The first length ``n >= 4`` at which ``buf[:n]`` ends with its CRC (function codes of unknown length).

    The CRC of a frame followed by its own CRC is 0, so one running CRC finds it in one pass.
    """
    crc = 0xFFFF
    for n, byte in enumerate(buf[:_MAX_FRAME], start=1):
        crc = (crc >> 8) ^ _TABLE[(crc ^ byte) & 0xFF]
        if n >= 4 and crc == 0:
            return n
    return None

