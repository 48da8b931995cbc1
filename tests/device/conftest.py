"""Shared by the device tests: a bare Modbus TCP client that sends raw PDUs over a real socket."""

import asyncio
import struct

import pytest


class RawClient:
    """A bare Modbus TCP client: MBAP framing only, so every byte of the request and the answer is the test's."""

    def __init__(self, reader, writer):
        self.reader, self.writer, self.tid = reader, writer, 0

    def send(self, unit, pdu):
        """Send one request PDU to ``unit``; returns its transaction id."""
        self.tid += 1
        self.writer.write(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, unit) + pdu)
        return self.tid

    async def receive(self, timeout=2.0):
        """``(transaction id, response PDU)``; ``asyncio.TimeoutError`` when nothing comes in time."""
        header = await asyncio.wait_for(self.reader.readexactly(7), timeout)
        tid, proto, length, _ = struct.unpack(">HHHB", header)
        assert proto == 0
        return tid, await self.reader.readexactly(length - 1)

    async def ask(self, unit, pdu, timeout=2.0):
        """Send one request and return the response PDU (its transaction id checked)."""
        tid = self.send(unit, pdu)
        got, answer = await self.receive(timeout)
        assert got == tid
        return answer


@pytest.fixture
async def raw_for():
    """``await raw_for(server)``: a :class:`RawClient` connected to a running server (closed after the test)."""
    writers = []

    async def connect(srv):
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        writers.append(writer)
        return RawClient(reader, writer)

    yield connect
    for writer in writers:
        writer.close()
