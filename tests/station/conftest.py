"""Fixtures of the station tests: a real emulator (Modbus on 127.0.0.1, port 0) with its station app."""

import pytest
from aiohttp.test_utils import TestClient, TestServer
from station_helpers import station_config

from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.station.app import make_app
from valve_emulator.station.core import Station


@pytest.fixture
async def station_for(tmp_path):
    """``await station_for(config, time_scale=..., token=...)``: (EmulatorServer, Station, TestClient)."""
    made = []

    async def make(config=None, *, time_scale=0.0, token=None, snapshots=None, backtrack=None):
        srv = EmulatorServer(config or station_config(), host="127.0.0.1", port=0, time_scale=time_scale)
        await srv.__aenter__()
        station = Station(srv.device, snapshots=snapshots or SnapshotStore(tmp_path / "snapshots"),
                          backtrack=backtrack)
        client = TestClient(TestServer(make_app(station, token=token), host="127.0.0.1", port=0))
        await client.start_server()
        made.append((srv, client))
        return srv, station, client

    yield make
    for srv, client in made:
        await client.close()
        await srv.__aexit__(None, None, None)

