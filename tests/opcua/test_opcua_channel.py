"""The channel between the device process and the OPC UA process: answers, refusals, notes, a closed peer."""

import asyncio
import socket
import time
from multiprocessing import resource_tracker

import numpy as np
import pytest

from valve_emulator.device.registers import RegisterValueError
from valve_emulator.opcua.channel import Channel, ChannelClosed
from valve_emulator.opcua.shared import COMPUTED, ImagePublisher, ImageReader


async def _pair(handlers_a, handlers_b):
    a_sock, b_sock = socket.socketpair()
    a, b = Channel(a_sock, handlers_a), Channel(b_sock, handlers_b)
    await a.open()
    await b.open()
    tasks = [asyncio.create_task(a.run()), asyncio.create_task(b.run())]
    return a, b, tasks


async def test_a_call_gets_the_answer_or_the_same_refusal_and_a_note_no_answer():
    noted = []

    def write(value):
        if value > 10:
            raise RegisterValueError(f"value {value} above 10")
        return value * 2

    async def slow(value):
        await asyncio.sleep(0.05)
        return value

    a, b, tasks = await _pair({}, {"write": write, "slow": slow, "note": noted.append})
    try:
        assert await a.call("write", 4) == 8
        with pytest.raises(RegisterValueError, match="value 11 above 10"):
            await a.call("write", 11)
        slow_answer = asyncio.create_task(a.call("slow", "late"))
        assert await a.call("write", 1) == 2   # a slow handler holds up no other call
        assert await slow_answer == "late"
        a.note("note", "hello")
        await asyncio.sleep(0.05)
        assert noted == ["hello"]
    finally:
        await a.close()
        await b.close()
        await asyncio.gather(*tasks, return_exceptions=True)


async def test_a_call_to_a_peer_that_closed_raises_channel_closed():
    never = asyncio.Event()

    async def hang():
        await never.wait()

    a, b, tasks = await _pair({}, {"hang": hang})
    pending = asyncio.create_task(a.call("hang"))
    await asyncio.sleep(0.05)
    await b.close()
    with pytest.raises(ChannelClosed):
        await asyncio.wait_for(pending, 5)
    await a.close()
    await asyncio.gather(*tasks, return_exceptions=True)


class _Bank:
    n, sample_time = 2, 0.5
    pv, op, mv, sp = (np.array([1.5, 2.5]), np.array([10.0, 20.0]), np.array([11.0, 21.0]),
                      np.array([3.0, 4.0]))


class _Device:
    bank, ticks, image = _Bank(), 7, bytearray(range(16))

    class scaling:   # noqa: N801 - the device's attribute
        has_controller = np.array([True, False])


def test_the_reader_sees_what_was_published_and_copies_only_a_new_publication():
    publisher = ImagePublisher(_Device())
    try:
        publisher.publish()
        reader = ImageReader(publisher.name, publisher.layout)
        # in one process both share a resource tracker, from which the reader has just taken the block
        resource_tracker.register(publisher.shm._name, "shared_memory")
        first = reader.read()
        assert (first.image, first.ticks, first.sample_time) == (bytes(range(16)), 7, 0.5)
        assert first.computed[COMPUTED.index("pv")].tolist() == [1.5, 2.5]
        assert first.computed[COMPUTED.index("sp")].tolist() == [3.0, 0.0]   # no controller: SP reads 0
        assert reader.read() is first   # nothing new: no copy
        publisher.device.image[0] = 99
        publisher.publish()
        assert reader.read().image[0] == 99 and publisher.copies == 2
        reader.close()
    finally:
        publisher.close()


def test_a_pinned_reader_sees_one_tick_and_the_header_says_which_and_when_it_ran():
    """A chunk of the OPC UA process's hand-off samples one tick however many the device publishes meanwhile
    (never half of one and half of the next), stamped with the time the device first published that tick: a write
    published later keeps the tick's time, a new tick gets its own."""
    device = _Device()
    device.image = bytearray(range(16))
    publisher = ImagePublisher(device)
    try:
        publisher.publish()
        reader = ImageReader(publisher.name, publisher.layout)
        resource_tracker.register(publisher.shm._name, "shared_memory")
        ran = reader.read().wall_time
        device.image[0] = 50   # a write: the same tick
        publisher.publish()
        assert reader.read().image[0] == 50 and reader.read().wall_time == ran
        with reader.pinned() as held:
            time.sleep(0.01)
            device.ticks, device.image[0] = 8, 60   # the device runs a tick meanwhile
            publisher.publish()
            with reader.pinned() as inner:
                assert inner is held
            assert reader.read() is held and (held.ticks, held.image[0]) == (7, 50)
        newer = reader.read()
        assert (newer.ticks, newer.image[0]) == (8, 60) and newer.wall_time > ran
        reader.close()
    finally:
        publisher.close()


def test_a_reader_pinned_at_a_tick_sees_that_tick_after_the_device_published_newer_ones():
    """A hand-off run late (after the device published the next ticks) samples the tick it is for while the block
    keeps it, the newest before it where the device published none for that tick, and never a newer one while an
    older is kept; a tick count that went back (a restored snapshot) leaves none of the ticks before it."""
    device = _Device()
    device.image = bytearray(16)
    publisher = ImagePublisher(device, slots=4)
    try:
        reader = ImageReader(publisher.name, publisher.layout)
        resource_tracker.register(publisher.shm._name, "shared_memory")
        for tick in (7, 8, 9, 11):   # tick 10 ran without a publication (ticks run as one call)
            device.ticks, device.image[0] = tick, tick
            publisher.publish()
        device.image[1] = 1   # a write after tick 11: the same tick's slot
        publisher.publish()
        assert (reader.read().ticks, reader.read().image[:2]) == (11, bytes([11, 1]))
        for asked, got in ((8, 8), (9, 9), (10, 9), (11, 11), (12, 11)):
            with reader.pinned(asked) as held:
                assert (held.ticks, held.image[0]) == (got, got)
                assert reader.read() is held
        with reader.pinned(7) as held:   # 7's slot (7 % 4) now holds 11: the block keeps nothing at or before 7
            assert held.ticks == 11
        device.ticks, device.image[0] = 9, 90   # went back
        publisher.publish()
        with reader.pinned(8) as held:   # the old 8 is not this run's 8
            assert (held.ticks, held.image[0]) == (9, 90)
        reader.close()
    finally:
        publisher.close()
