"""Fixtures of the station tests: a real emulator (Modbus on 127.0.0.1, port 0) with its station app."""

import pytest
from aiohttp.test_utils import TestClient, TestServer
from station_helpers import station_config

from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.station.app import make_app
from valve_emulator.station.core import Station
from valve_emulator.testing import Emulator


@pytest.fixture
async def station_for(tmp_path):
    """``await station_for(config, time_scale=..., token=..., users=...)``: (EmulatorServer, Station, TestClient).

    The device is the testing kit's :class:`~valve_emulator.testing.Emulator`: ``time_scale=0`` (the default) its
    manual clock, a test steps it with ``srv.device.advance``; above 0 its real clock at that speed.
    """
    made = []

    async def make(config=None, *, time_scale=0.0, token=None, users=None, snapshots=None, backtrack=None):
        emu = Emulator(config or station_config(), clock="real" if time_scale else "manual",
                       time_scale=time_scale or 1.0)
        await emu.start()
        station = Station(emu.device, snapshots=snapshots or SnapshotStore(tmp_path / "snapshots"),
                          backtrack=backtrack)
        client = TestClient(TestServer(make_app(station, token=token, users=users), host="127.0.0.1", port=0))
        await client.start_server()
        made.append((emu, client))
        return emu.server, station, client

    yield make
    for emu, client in made:
        await client.close()
        await emu.stop()
