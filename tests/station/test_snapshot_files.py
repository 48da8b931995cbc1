"""Broken snapshot files: the station starts anyway, lists them, and refuses to restore one with an error naming
the file and what is wrong; the running state is unchanged."""

import json

import numpy as np
import pytest
from hostile_input import rewrite_snapshot
from station_helpers import JSON, PLANT, station_config

from valve_emulator.config import load_server, server_from_mapping
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.simulation.loop import LoopBank

pytestmark = pytest.mark.usefixtures("no_task_leak")


async def _snapshot_of(config, path):
    """Write a snapshot file of a device built from ``config`` (another station's file)."""
    async with EmulatorServer(config, host="127.0.0.1", port=0, time_scale=0) as other:
        other.device.advance(3)
        other.device.snapshot(path.stem).save(path)


def _everything(srv):
    """The device's complete state: image, tick count, every array and number of the bank."""
    state = srv.device.bank.state()
    return bytes(srv.device.image), srv.device.ticks, {k: (v.tobytes() if isinstance(v, np.ndarray) else repr(v))
                                                       for k, v in state.items()}


def _three_loops():
    loop = {"valve": {"S": 3.0, "J": 1.0}, "plant": PLANT}
    return server_from_mapping({"device": {"tick": 0.1}, "loops": [{"unit": u, **loop} for u in (1, 2, 3)]})


def _other_units():
    loop = {"valve": {"S": 3.0, "J": 1.0}, "plant": PLANT}
    return server_from_mapping({"device": {"tick": 0.1}, "loops": [{"unit": u, **loop} for u in (5, 6)]})


async def test_broken_snapshot_files_are_refused_naming_the_file_and_the_state_is_unchanged(station_for, tmp_path):
    folder = tmp_path / "snapshots"
    srv, station, client = await station_for(snapshots=SnapshotStore(folder))
    srv.device.advance(20)
    assert (await client.post("/api/snapshots", data=json.dumps({"name": "good"}), headers=JSON)).status == 201
    good = folder / "good.npz"
    (folder / "truncated.npz").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    rewrite_snapshot(good, folder / "version.npz", header={"format": 2})
    rewrite_snapshot(good, folder / "ticks.npz", header={"ticks": "many"})
    rewrite_snapshot(good, folder / "infinite.npz", header={"time": 1e400})     # json writes Infinity
    rewrite_snapshot(good, folder / "huge.npz", header={"time": 12345.5},
                     edit=lambda text: text.replace("12345.5", "1e400"))
    with np.load(good) as data:
        x = data["bank:_plant/_x"]
    rewrite_snapshot(good, folder / "nan.npz", arrays={"bank:_plant/_x": np.full_like(x, np.nan)})
    rewrite_snapshot(good, folder / "head.npz", arrays={"bank:_plant/_head": np.array([10**9])})   # was a segfault
    bank = json.loads(json.loads(str(np.load(good)["__header__"]))["bank"])
    rewrite_snapshot(good, folder / "counter.npz", header={"bank": json.dumps({**bank, "k": "many"})})
    rewrite_snapshot(good, folder / "steps.npz", header={"bank": json.dumps({**bank, "_sp_steps": [[["x", 1]]]})})
    device = json.loads(str(np.load(good)["__header__"]))["device"]
    ramps = [{"index": 9, "quantity": "S"}]
    rewrite_snapshot(good, folder / "ramps.npz", header={"device": {**device, "ramps": ramps}})
    await _snapshot_of(_three_loops(), folder / "three.npz")
    await _snapshot_of(_other_units(), folder / "other.npz")
    expected = {   # name -> what the error must say besides the file's path
        "truncated": "not a readable snapshot file", "version": "snapshot format 2",
        "ticks": "'ticks' must be a whole number", "infinite": "Infinity is not a JSON number",
        "huge": "'time' is inf",
        "nan": "state field _plant/_x holds nan", "head": "_plant/_head = array([1000000000]) is outside 0..",
        "counter": "state field k: saved 'many' is not of the kind of", "steps": "state field _sp_steps: saved",
        "ramps": "malfunction ramps do not fit",
        "three": "another configuration", "other": "another configuration",
    }
    srv.device.advance(7)
    before = _everything(srv)
    for name, what in expected.items():
        resp = await client.post(f"/api/snapshots/{name}/restore", data="{}", headers=JSON)
        assert resp.status == 409, (name, await resp.text())
        error = (await resp.json())["error"]
        assert str(folder / f"{name}.npz") in error and what in error, (name, error)
        assert _everything(srv) == before, name
    # a restart reads the folder: the good file loads, the unreadable ones are listed with their reason
    listing = await (await client.get("/api/snapshots")).json()
    assert {b["name"] for b in listing["broken"]} == {"truncated", "version", "ticks", "infinite", "huge"}
    restarted = SnapshotStore(folder)
    assert "good" in restarted and set(restarted.broken) == {"truncated", "version", "ticks", "infinite", "huge"}
    # the good one still restores, and a broken one can be deleted
    assert (await client.post("/api/snapshots/good/restore", data="{}", headers=JSON)).status == 200
    assert (await client.delete("/api/snapshots/truncated", headers=JSON)).status == 200
    assert not (folder / "truncated.npz").exists()


@pytest.mark.parametrize("config", ["configs/plant_room.yaml", "station"])
def test_only_the_declared_state_fields_hold_non_finite_numbers_or_change_their_integers(config):
    """The allowances the restore checks rely on: every other number of a bank's state is finite, and every
    other integer stays as the configuration set it, at the start and after running with noise and a set-point
    change (a stale list would refuse good snapshots)."""
    cfg = station_config(noise=0.05) if config == "station" else load_server(config)
    bank = LoopBank(cfg.loops, dt=cfg.device.tick)
    start = bank.state()
    bank.set_sp(0, 1.0)
    bank.run(300)
    for path, value in bank.state().items():
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and path not in LoopBank.NON_FINITE_STATE:
            assert np.isfinite(value).all(), path
        integers = isinstance(value, np.ndarray) and value.dtype.kind in "iu" or type(value) is int
        if integers and path in start and path not in bank.dynamic_int_state():
            assert np.array_equal(value, start[path]), path
