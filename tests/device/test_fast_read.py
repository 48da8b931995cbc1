"""The FC3 / FC4 fast path answers exactly as the general path does: the same bytes, the same counters.

:meth:`EmulatorServer.handle` answers a well-formed register read of mapped registers straight from the
register image, and a connection answers a frame that arrived alone without buffering it. Both are shortcuts
for speed, so their only observable property is that nothing observable changes: every read the general
path answers (values, exception codes, transaction ids, unit ids) and every count it keeps must come out the
same. Checked on thousands of random reads (addresses near the edges of the map and of the blocks, counts
0..130, units with one loop, several loops, none) in-process, and over a real socket one frame at a time
against the same frames pipelined in one burst (which the general path serves).
"""

import asyncio
import random
import struct

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import BLOCK_STRIDE, COMM_BASE, N_REGISTERS
from valve_emulator.device.roles import UNAUTHENTICATED
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

_LOOP = {"plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}}


def _config():
    # units 1 and 2 with one loop each (2 with a PI controller); units 3.. carry 4 loops each (blocks)
    # error_rate: half the random reads are refused, and the error budget would slow the socket test down
    return server_from_mapping({"device": {"tick": 0.1, "error_rate": 100000}, "loops": [
        {"unit": 1, **_LOOP}, {"unit": 2, **_LOOP, "controller": {"kc": 0.4, "ti": 2.0}}],
        "fleet": {"count": 8, "first_unit": 3, "loops_per_unit": 4, "base": _LOOP, "seed": 1}})


def _frames(n, seed=0):
    """``n`` random FC3 / FC4 request frames: units 0..6 (5 and 6 and 0 have no loop), addresses near the
    edges that matter, counts 0..130, random transaction ids."""
    rnd = random.Random(seed)
    edges = [0, 1, N_REGISTERS - 1, N_REGISTERS, BLOCK_STRIDE - 1, BLOCK_STRIDE, 3 * BLOCK_STRIDE + 5,
             4 * BLOCK_STRIDE - 1, COMM_BASE - 1, COMM_BASE, COMM_BASE + 0x10, 0xFFFF]
    out = []
    for _ in range(n):
        address = rnd.choice(edges) + rnd.randint(-3, 3) if rnd.random() < 0.6 else rnd.randint(0, 0xFFFF)
        address = min(max(address, 0), 0xFFFF)
        count = rnd.choice([0, 1, 2, 10, 28, 32, 125, 126, 130, rnd.randint(0, 130)])
        if rnd.random() < 0.4:   # a read a poller makes: inside the map of one block
            address = rnd.randint(0, N_REGISTERS - 1) + BLOCK_STRIDE * rnd.randint(0, 3)
            count = rnd.randint(1, N_REGISTERS - address % BLOCK_STRIDE)
        out.append(struct.pack(">HHHBBHH", rnd.randint(0, 0xFFFF), 0, 6, rnd.randint(0, 6), rnd.choice((3, 4)),
                               address, count))
    return out


def _general(srv):
    """``frame -> answer`` by the general path (the fast path switched off for the call)."""
    def answer(frame):
        fast, srv._read_fast = srv._read_fast, lambda frame: None
        known, srv._reads = srv._reads, {}   # and nothing remembered
        try:
            return srv.handle(frame, UNAUTHENTICATED)
        finally:
            srv._read_fast, srv._reads = fast, known
    return answer


async def test_every_read_gets_the_general_paths_bytes_and_counts(fake_bank_cls):
    config = _config()
    async with EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0) as srv:
        general, fast_hits = _general(srv), 0
        for frame in _frames(6000):
            requests, exceptions = srv.requests, srv.exceptions
            got = srv.handle(frame, UNAUTHENTICATED)
            counted = (srv.requests - requests, srv.exceptions - exceptions)
            # the same read again, from another transaction: a valid one is answered from the reads remembered
            again = frame[:1] + bytes((frame[1] ^ 0xFF,)) + frame[2:]
            assert srv.handle(again, UNAUTHENTICATED) == again[:2] + got[2:]
            assert srv.requests - requests == 2 * counted[0]
            fast_hits += srv._read_fast(frame) is not None
            requests, exceptions = srv.requests, srv.exceptions
            want = general(frame)
            assert got == want, (frame.hex(), got.hex(), want.hex())
            assert counted == (srv.requests - requests, srv.exceptions - exceptions), frame.hex()
        # the random reads exercise both paths, the fast one for a good share of them
        assert 500 < fast_hits < 3000, fast_hits
        assert 0 < len(srv._reads) <= fast_hits   # only valid reads are remembered


async def test_frames_sent_alone_and_pipelined_get_the_same_answers(fake_bank_cls):
    config = _config()
    frames = _frames(400, seed=1)
    async with EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0) as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        try:
            async def answer():
                header = await asyncio.wait_for(reader.readexactly(6), 5.0)
                return header + await reader.readexactly(struct.unpack(">H", header[4:])[0])

            alone = []
            for frame in frames:           # one outstanding request: each arrives on its own
                writer.write(frame)
                alone.append(await answer())
            writer.write(b"".join(frames))  # one burst: the buffered path cuts and answers them
            burst = [await answer() for _ in frames]
            # and one frame split across two writes
            writer.write(frames[0][:5])
            await writer.drain()
            await asyncio.sleep(0.05)
            writer.write(frames[0][5:])
            split = await answer()
        finally:
            writer.close()
    assert alone == burst
    assert split == alone[0]
    assert [a[:2] for a in alone] == [f[:2] for f in frames]   # every transaction id answered, in order
