"""Shared by the OPC UA and Modbus/TLS tests: a device with one controlled loop and one open loop, and OPC UA
servers that several tests of a module share."""

import contextlib

import pytest
import pytest_asyncio

from valve_emulator.config import server_from_mapping
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.station.core import Station

from .modes import MODES, serve_opcua

DEVICE = {
    "device": {"tick": 0.1},
    "loops": [
        {"unit": 1, "name": "FIC101", "valve": {"S": 5.0, "J": 2.0},
         "plant": {"fopdt": {"gain": 2.0, "tau": 10.0, "delay": 1.0}, "pv_range": [0.0, 50.0], "units": "m3/h"},
         "controller": {"kc": 0.3, "ti": 10.0}},
        {"unit": 2, "name": "XV2", "valve": {"S": 3.0, "J": 1.0},
         "plant": {"fopdt": {"gain": 1.0, "tau": 5.0, "delay": 0.5}, "pv_range": [-10.0, 10.0]}},
    ],
}


@pytest.fixture
def config():
    return server_from_mapping(DEVICE)


@pytest.fixture(params=MODES)
def opcua_mode(request):
    """Each OPC UA test runs twice: in the device's process and in a process of its own."""
    return request.param


@pytest.fixture(scope="module", params=MODES)
def shared_mode(request):
    """:func:`opcua_mode` for a server that the tests of one module share (one server per mode, not per test:
    building asyncua's standard address space costs about a second per server)."""
    return request.param


#: Marks a test that uses a module's shared server: it runs in the module's event loop, the server's.
ON_A_SHARED_SERVER = pytest.mark.asyncio(loop_scope="module")


@contextlib.asynccontextmanager
async def device_with_opcua(mode, *, with_station=True, **settings):
    """(Modbus server, station, OPC UA server) on one device of :data:`DEVICE` (the station ``None`` without
    one), time frozen (the test steps it with ``device.advance``); ``settings`` go to the OPC UA server."""
    config = server_from_mapping(DEVICE)
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        station = Station(srv.device, snapshots=SnapshotStore()) if with_station else None
        async with serve_opcua(mode, srv.device, loops=config.loops, port=0, station=station, **settings) as opc:
            yield srv, station, opc


@contextlib.contextmanager
def restored(device):
    """Put ``device`` back as it was on entry once the test is done with it: a test on a shared server leaves
    the next one the device it found (time, loops and pending writes)."""
    before = device.snapshot("before the test")
    try:
        yield
    finally:
        device.restore(before)


def shared_server(**settings):
    """A module-scoped fixture: one :func:`device_with_opcua` per mode for the module's tests that only read
    the device or change what :func:`restored` puts back."""

    @pytest_asyncio.fixture(scope="module", loop_scope="module")
    async def server(shared_mode):
        async with device_with_opcua(shared_mode, **settings) as served:
            yield served

    return server
