"""The OPC UA process decodes a float32 variable of every loop at once, once per tick (``OpcUaServer._column``):
each value the one decoding it alone gives (the double the tick computed where it still encodes to the image's
float32, else the shortest decimal that reads back as the image's float32), in either word order, and a new tick
is decoded anew."""

import copy
import struct
from multiprocessing import resource_tracker

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import CDAB
from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua.remote import ChildSpec, RemoteSource
from valve_emulator.opcua.server import VARIABLES, OpcUaServer
from valve_emulator.opcua.shared import COMPUTED, ImagePublisher
from valve_emulator.opcua.source import LocalSource

from .conftest import DEVICE

FLOATS = [v for v in VARIABLES if v.name in COMPUTED]


class _OneByOne(RemoteSource):
    """The same shared image without a snapshot: every value decoded alone."""

    @property
    def snapshot(self):
        return None


def _spec(publisher, device, loops):
    local = LocalSource(device)
    return ChildSpec(shm_name=publisher.name, layout=publisher.layout, units=tuple(local.units),
                     offsets=local.offsets, scaling=local.scaling, dt=local.dt, period=device.period,
                     has_station=False, has_alarms=False, raised=(), loops=tuple(loops), host="127.0.0.1", port=0,
                     security=None, history=None, history_path=":memory:", log_level=0)


def _put_float32(device, index, var, value):
    """Write ``value`` as the float32 of ``var``'s register of loop ``index`` into the device's image (a write the
    tick has not seen: the image no longer holds the tick's double)."""
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    if device.scaling.word_order is CDAB:
        high, low = low, high
    at = int(device.offsets[index]) + 2 * var.read.address
    device.image[at:at + 4] = struct.pack(">HH", high, low)


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")   # the one-by-one path's
@pytest.mark.parametrize("word_order", ["ABCD", "CDAB"])
async def test_every_loops_float32_values_decoded_at_once_are_those_decoded_one_by_one(word_order):
    mapping = copy.deepcopy(DEVICE)
    mapping["device"]["word_order"] = word_order
    mapping["loops"] = [dict(mapping["loops"][k % 2], name=f"L{k}", unit=1 + k) for k in range(12)]
    config = server_from_mapping(mapping)
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        device = srv.device
        device.advance(3)
        bank = device.bank
        publisher = ImagePublisher(device)
        try:
            publisher.publish()
            spec = _spec(publisher, device, config.loops)
            at_once, alone = RemoteSource(spec), _OneByOne(spec)
            resource_tracker.register(publisher.shm._name, "shared_memory")   # both readers unregistered it
            resource_tracker.register(publisher.shm._name, "shared_memory")
            servers = [OpcUaServer(source, loops=config.loops) for source in (at_once, alone)]
            n = len(config.loops)

            def values(server):
                return [[server.value(k, var) for var in FLOATS] for k in range(n)]

            def same(a, b):
                return all(x == y or (np.isnan(x) and np.isnan(y)) for xs, ys in zip(a, b, strict=True)
                           for x, y in zip(xs, ys, strict=True))

            first = values(servers[0])
            assert same(first, values(servers[1]))
            assert all(isinstance(x, float) for xs in first for x in xs)
            # a write since the tick, NaN, and a double beyond float32 (its float32 infinity): each as decoded alone
            pv, op = (next(v for v in FLOATS if v.name == name) for name in ("pv", "op"))
            _put_float32(device, 2, pv, 61.3)
            _put_float32(device, 3, op, float("nan"))
            bank.pv[0] = 1.3   # the tick's double where its float32 is the image's: not 1.2999999523...
            _put_float32(device, 0, pv, 1.3)
            bank.pv[4] = 1e39
            _put_float32(device, 4, pv, float("inf"))
            bank.op[5] = float("nan")
            publisher.publish()
            second = values(servers[0])
            assert same(second, values(servers[1]))
            assert second[0][FLOATS.index(pv)] == 1.3
            assert second[2][FLOATS.index(pv)] == 61.3   # the written value, not 61.29999923706055
            assert np.isnan(second[3][FLOATS.index(op)]) and second[4][FLOATS.index(pv)] == 1e39
            assert second != first   # a new publication: decoded anew, not the columns of the one before
            at_once.close()
            alone.close()
        finally:
            publisher.close()
