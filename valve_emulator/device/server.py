"""Modbus TCP adapter: serves the register image of a :class:`~valve_emulator.device.tick.Device`.

The only module that imports pymodbus on the server side or knows Modbus exception codes.

Decision: pymodbus for the PDU layer only, our own asyncio server for the rest
------------------------------------------------------------------------------
pymodbus 3.16's server drops every request but the first when several frames arrive in one TCP segment
(its receive buffer is cleared on send), logs a full traceback for an unknown unit id, runs datastore
"actions" twice for function code 6 and blocks the owner's own writes to client-read-only registers. Fixing
that inside its connection and datastore classes would mean overriding private methods of several classes.
So this module runs a plain ``asyncio`` TCP server with MBAP framing (~40 lines) and uses pymodbus where it
is good: decoding request PDUs (:class:`pymodbus.pdu.DecodePDU`, which validates quantities) and encoding
write responses, exception responses and MBAP headers (:class:`pymodbus.framer.FramerSocket`). Read
responses are the byte count plus a slice of the precomputed big-endian register image, with no
per-register work.

Framing: every complete MBAP frame in the receive buffer is answered, in order, and all answers to one
segment go out in one write, so pipelined requests work; a partial frame waits for more data. A frame with
a protocol id other than 0 or a length outside 2..254 cannot be resynchronised: the connection is closed.

Answers (exception codes):

- unit id without a loop: ``0x0B`` gateway target device failed to respond (logged at DEBUG, no traceback).
  Only the configured unit ids answer; there is no wildcard unit.
- function codes other than 3, 4, 6, 16, 23: ``0x01`` illegal function.
- ``read_only`` mode: every write function code (6, 16, 23) gets ``0x01`` illegal function (the server
  does not offer writing at all), and nothing changes.
- read/write outside the map, an FC4 read over an unmapped input address, a write to a read-only register,
  to a controller register of a loop without controller, to an instructor register without permission
  (``instructor_writes`` off, or the client's IP not in ``instructor_hosts``), or to OP while the internal
  controller is in auto: ``0x02`` illegal data address; nothing changes.
- a value out of range or a malformed quantity/byte count: ``0x03`` illegal data value; nothing changes
  (a multi-register write is checked completely before any of it is applied).
- an unexpected failure inside the emulator (a bug): ``0x04`` server device failure, logged with traceback.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import time
from typing import Any, Awaitable, Callable

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse
from pymodbus.pdu.register_message import WriteMultipleRegistersResponse, WriteSingleRegisterResponse

from valve_emulator.device.registers import (
    RegisterAccessError,
    RegisterAddressError,
    RegisterError,
    RegisterValueError,
    check_read,
)
from valve_emulator.device.tick import Device

__all__ = ["EmulatorServer"]

_log = logging.getLogger(__name__)

_READS = {3: "holding", 4: "input"}
_WRITES = frozenset({6, 16, 23})
_SUPPORTED = frozenset(_READS) | _WRITES
_MAX_WRITE = {16: 123, 23: 121}  # register counts allowed by the Modbus spec
_CODE_OF = ((RegisterValueError, ExcCodes.ILLEGAL_VALUE), (RegisterAccessError, ExcCodes.ILLEGAL_ADDRESS),
            (RegisterAddressError, ExcCodes.ILLEGAL_ADDRESS))


class _Refused(Exception):
    """Internal: answer with exception ``code``."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code


class EmulatorServer:
    """The emulator as a Modbus TCP server: ``async with EmulatorServer(config) as srv: ...``.

    Parameters
    ----------
    config : ``ServerConfig`` (device settings and one loop per unit id).
    host, port : where to listen; ``port=0`` picks a free port, read it back from :attr:`port`.
    time_scale : see :class:`~valve_emulator.device.tick.Device` (``inf`` fastest, ``0`` frozen).
    bank : an existing ``LoopBank`` (default: built from ``config``).
    clock, sleep, jitter_size : see :class:`~valve_emulator.device.tick.Device` (fake time in tests).

    A bind failure raises ``OSError`` after the tick task has been stopped again.
    """

    def __init__(self, config: Any, *, host: str = "127.0.0.1", port: int = 0, time_scale: float = 1.0,
                 bank: Any = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep, jitter_size: int = 4096) -> None:
        self.config = config
        self.host = host
        self.port = port
        self.device = Device.from_config(config, bank=bank, time_scale=time_scale, clock=clock, sleep=sleep,
                                         jitter_size=jitter_size)
        dev = config.device
        self._read_only = bool(dev.read_only)
        self._instructor = bool(dev.instructor_writes)
        self._instructor_hosts = frozenset(_normalise_ip(h) for h in dev.instructor_hosts)
        self._decoder = DecodePDU(is_server=True)
        self._framer = FramerSocket(self._decoder)
        self._server: asyncio.Server | None = None
        self._connections: set[_Connection] = set()
        self.requests = 0
        self.exceptions = 0

    @property
    def units(self) -> tuple[int, ...]:
        return self.device.units

    def instructor_allowed(self, peer_ip: str) -> bool:
        """May a client at ``peer_ip`` write the instructor registers?"""
        if not self._instructor:
            return False
        return not self._instructor_hosts or _normalise_ip(peer_ip) in self._instructor_hosts

    # --- lifecycle ----------------------------------------------------------------------------------

    async def start(self) -> None:
        await self.device.start()
        try:
            loop = asyncio.get_running_loop()
            self._server = await loop.create_server(lambda: _Connection(self), self.host, self.port)
        except BaseException:
            await self.device.stop()  # no half-started server: the tick task must not outlive us
            raise
        self.port = self._server.sockets[0].getsockname()[1]
        _log.info("serving units %s on %s:%d", list(self.units), self.host, self.port)

    async def stop(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
            for conn in list(self._connections):
                conn.transport.abort()
            await server.wait_closed()
        await self.device.stop()

    async def __aenter__(self) -> "EmulatorServer":
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()

    # --- one request --------------------------------------------------------------------------------

    def handle(self, frame: bytes, instructor: bool) -> bytes:
        """Answer one complete MBAP ``frame`` (header + PDU) with a complete response frame."""
        self.requests += 1
        tid, unit, fc = (frame[0] << 8) | frame[1], frame[6], frame[7]
        try:
            index = self.device.unit_index.get(unit)
            if index is None:
                raise _Refused(ExcCodes.GATEWAY_NO_RESPONSE, f"no loop on unit {unit}")
            if fc not in _SUPPORTED:
                raise _Refused(ExcCodes.ILLEGAL_FUNCTION, f"function code {fc} not supported")
            if self._read_only and fc in _WRITES:
                raise _Refused(ExcCodes.ILLEGAL_FUNCTION, "server is read-only")
            pdu = self._decoder.decode(frame[7:])
            if pdu is None:
                raise _Refused(ExcCodes.ILLEGAL_VALUE, "malformed request")
            payload = self._execute(fc, pdu, len(frame) - 7, index, instructor)
        except RegisterError as exc:
            code = next(c for cls, c in _CODE_OF if isinstance(exc, cls))
            payload = self._refuse(fc, code, unit, exc)
        except _Refused as exc:
            payload = self._refuse(fc, exc.code, unit, exc)
        except Exception as exc:  # a bug, not a client error: say so loudly, answer, keep serving
            _log.exception("unit %d fc %d: request failed", unit, fc)
            payload = self._refuse(fc, ExcCodes.DEVICE_FAILURE, unit, exc)
        return self._framer.encode(payload, unit, tid)

    def _refuse(self, fc: int, code: int, unit: int, reason: Exception) -> bytes:
        self.exceptions += 1
        _log.debug("unit %d fc %d -> exception 0x%02X: %s", unit, fc, code, reason)
        response = ExceptionResponse(fc, code)
        return bytes((response.function_code,)) + response.encode()

    def _read(self, fc: int, table: str, index: int, address: int, count: int) -> bytes:
        check_read(table, address, count)
        start = index * self.device.stride + 2 * address
        return bytes((fc, 2 * count)) + self.device.image[start:start + 2 * count]

    def _execute(self, fc: int, pdu: Any, pdu_len: int, index: int, instructor: bool) -> bytes:
        if fc in _READS:
            return self._read(fc, _READS[fc], index, pdu.address, pdu.count)
        device = self.device
        if fc == 6:
            device.write(index, pdu.address, pdu.registers, instructor=instructor)
            response = WriteSingleRegisterResponse(address=pdu.address, registers=pdu.registers)
            return b"\x06" + response.encode()
        # pymodbus decodes the write quantity but leaves checking it against the byte count to its
        # datastore layer, which we do not use: check count, byte count and the bytes actually sent.
        if fc == 16:
            count, nbytes, header = pdu.count, pdu.byte_count, 6
        else:
            count, nbytes, header = pdu.write_count, pdu.write_byte_count, 10
        if not (1 <= count <= _MAX_WRITE[fc] and nbytes == 2 * count == pdu_len - header):
            raise _Refused(ExcCodes.ILLEGAL_VALUE, f"write count {count} / byte count {nbytes} inconsistent")
        if fc == 16:
            device.write(index, pdu.address, pdu.registers, instructor=instructor)
            return b"\x10" + WriteMultipleRegistersResponse(address=pdu.address, count=count).encode()
        check_read("holding", pdu.read_address, pdu.read_count)  # refuse before writing anything
        device.write(index, pdu.write_address, pdu.write_registers, instructor=instructor)
        return self._read(23, "holding", index, pdu.read_address, pdu.read_count)


class _Connection(asyncio.Protocol):
    """One client: MBAP framing over a byte stream, every complete frame answered in order."""

    def __init__(self, server: EmulatorServer) -> None:
        self.server = server
        self.transport: asyncio.Transport
        self._buf = bytearray()
        self._instructor = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        peer = transport.get_extra_info("peername")
        self._instructor = self.server.instructor_allowed(peer[0] if peer else "")
        self.server._connections.add(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.server._connections.discard(self)

    # A client that pipelines requests but does not read the answers must not fill our memory.
    def pause_writing(self) -> None:
        self.transport.pause_reading()

    def resume_writing(self) -> None:
        self.transport.resume_reading()

    def data_received(self, data: bytes) -> None:
        buf = self._buf
        buf += data
        end_of_data, pos, answers = len(buf), 0, []
        while end_of_data - pos >= 7:
            length = (buf[pos + 4] << 8) | buf[pos + 5]
            if buf[pos + 2] or buf[pos + 3] or not 2 <= length <= 254:
                _log.warning("closing connection: not a Modbus TCP frame (%s)", bytes(buf[pos:pos + 7]).hex())
                self.transport.close()
                buf.clear()
                return
            end = pos + 6 + length
            if end > end_of_data:
                break  # partial frame: wait for the rest
            answers.append(self.server.handle(bytes(buf[pos:end]), self._instructor))
            pos = end
        del buf[:pos]
        if answers:
            self.transport.write(b"".join(answers))


def _normalise_ip(host: str) -> str:
    """Canonical text of an IP address (IPv4-mapped IPv6 as IPv4); other strings unchanged."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    mapped = getattr(ip, "ipv4_mapped", None)
    return str(mapped or ip)
