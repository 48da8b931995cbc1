"""Throughput: the emulator answers reads at least 0.9x as fast as a plain pymodbus SimDevice server.

Both servers run in this event loop and are driven by the same lean raw-socket client (one connection,
one outstanding 10-register read at a time), alternately, best of three rounds each, so machine noise
hits both alike.
"""

import asyncio
import math
import struct
import time

import pytest
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import N_REGISTERS
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

REQUESTS = 1500


async def _rate(port: int, n: int = REQUESTS) -> float:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        start = time.perf_counter()
        for tid in range(n):
            writer.write(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0, 10))
            header = await reader.readexactly(7)
            body = await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
            assert body[0] == 3 and body[1] == 20
        return n / (time.perf_counter() - start)
    finally:
        writer.close()
        await writer.wait_closed()


async def test_read_throughput_not_below_plain_pymodbus():
    plain = ModbusTcpServer(SimDevice(1, simdata=[SimData(0, count=N_REGISTERS, values=0,
                                                          datatype=DataType.REGISTERS)]),
                            address=("127.0.0.1", 0))
    await plain.serve_forever(background=True)
    cfg = server_from_mapping({"device": {"tick": 0.1},
                               "loops": [{"unit": 1, "plant": {"num": [1.0], "den": [10.0, 1.0]}}]})
    try:
        async with EmulatorServer(cfg, time_scale=1.0) as ours:
            plain_port = plain.transport.sockets[0].getsockname()[1]
            rates = {"plain": [], "ours": []}
            for _ in range(3):
                rates["plain"].append(await _rate(plain_port))
                rates["ours"].append(await _rate(ours.port))
    finally:
        await plain.shutdown()
    best = {k: max(v) for k, v in rates.items()}
    assert best["ours"] >= 0.9 * best["plain"], best
    assert math.isfinite(best["ours"])
