"""A log of every request a server saw, for tests that assert what a client under test did.

Pure (no pymodbus, no asyncio). :class:`TrafficLog` is off unless a server is given one
(``EmulatorServer.traffic``); the testing kit (:mod:`valve_emulator.testing`) always gives one, so a test can
say "it never wrote OP while in auto" or "it polls every 500 ms" from :class:`Request` rows::

    time       simulated seconds when the request arrived (the device's sample time)
    wall       time.monotonic() when it arrived
    client     "ip:port" of the TCP connection ("" on a serial line)
    unit       unit id the request addressed
    function   function code (3 read holding registers, 6 write single register, ...)
    address    first register or coil it read or wrote (FC23: the written one; FC8, FC43: None)
    count      how many (FC5, 6, 22: 1)
    exception  the exception code it was answered with; None for a normal answer, and None with
               ``answered=False`` for a request a communication fault swallowed
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

from valve_emulator.device.pdu import BIT_READ_FUNCTIONS, BIT_WRITE_FUNCTIONS, READ_FUNCTIONS, WRITE_FUNCTIONS

__all__ = ["Request", "TrafficLog", "request_span"]

_SPANNED = READ_FUNCTIONS | BIT_READ_FUNCTIONS | WRITE_FUNCTIONS | BIT_WRITE_FUNCTIONS


@dataclass(frozen=True, slots=True)
class Request:
    """One request as the server saw it (see the module docstring)."""

    time: float
    wall: float
    client: str
    unit: int
    function: int
    address: int | None
    count: int | None
    exception: int | None = None
    answered: bool = True

    @property
    def is_write(self) -> bool:
        """Did the request write (FC 5, 6, 15, 16, 22, 23)?"""
        return self.function in WRITE_FUNCTIONS or self.function in BIT_WRITE_FUNCTIONS


def request_span(pdu: bytes) -> tuple[int | None, int | None]:
    """``(address, count)`` a request PDU reads or writes (FC23: its write half); ``(None, None)`` for the
    function codes without one (8, 43, unknown) and for a PDU too short to say."""
    fc = pdu[0] if pdu else 0
    if fc not in _SPANNED:
        return None, None
    if fc == 23:
        return (_u16(pdu, 5), _u16(pdu, 7)) if len(pdu) >= 9 else (None, None)
    if len(pdu) < 5:
        return None, None
    return _u16(pdu, 1), (1 if fc in (5, 6, 22) else _u16(pdu, 3))


def _u16(pdu: bytes, at: int) -> int:
    return (pdu[at] << 8) | pdu[at + 1]


class TrafficLog:
    """The requests a server saw, oldest first (``len``, iteration, ``log[i]``, ``clear``).

    ``limit`` bounds the memory a long test can use: beyond it the oldest rows are dropped (:attr:`dropped`
    counts them). ``clock`` gives the simulated time of an arriving request.
    """

    def __init__(self, clock, *, limit: int = 1_000_000) -> None:
        self._clock = clock
        self.limit = int(limit)
        self.dropped = 0
        self._rows: deque[Request] = deque(maxlen=self.limit)

    def arrival(self) -> tuple[float, float]:
        """``(simulated, wall)`` time now: taken when a request arrives, before it is carried out (a
        ``step`` write runs ticks before it is answered)."""
        return float(self._clock()), time.monotonic()

    def note(self, client: str, unit: int, pdu: bytes, response: bytes | None, *,
             arrived: tuple[float, float] | None = None) -> None:
        """Record request ``pdu`` of ``unit`` answered with ``response`` (``None``: nothing was sent);
        ``arrived`` from :meth:`arrival` (default now)."""
        if len(self._rows) == self.limit:
            self.dropped += 1
        sim, wall = self.arrival() if arrived is None else arrived
        address, count = request_span(pdu)
        exception = response[1] if response is not None and len(response) > 1 and response[0] & 0x80 else None
        self._rows.append(Request(sim, wall, client, unit, pdu[0] if pdu else 0, address, count, exception,
                                  response is not None))

    def clear(self) -> None:
        self._rows.clear()

    def __len__(self) -> int:
        return len(self._rows)

    def __iter__(self) -> Iterator[Request]:
        return iter(list(self._rows))

    def __getitem__(self, index: int) -> Request:
        return self._rows[index]

    def __repr__(self) -> str:
        return f"TrafficLog({len(self._rows)} requests)"
