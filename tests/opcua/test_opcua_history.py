"""HistoryRead of PV, OP, SP and MV over the last period (``OpcUaServer(history=...)``, ``serve
--opcua-history``); asyncua's client in process."""

import asyncio
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import Client, ua

from valve_emulator.cli import main
from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua import NAMESPACE
from valve_emulator.opcua.history import HistoryError, history_seconds

from .modes import serve_opcua
from .test_opcua_interop import start_serve, stop


async def _variables(client, unit, name):
    ns = await client.get_namespace_index(NAMESPACE)
    loop = await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit{unit}", f"{ns}:{name}"])
    return {(await c.read_browse_name()).Name: c for c in await loop.get_children()}


async def _ticks(device, times, *, each=10):
    """``times`` rounds of ``each`` lockstep ticks, letting the publisher hand each round's values on."""
    for _ in range(times):
        device.advance(each)
        await asyncio.sleep(0.1)


async def test_history_read_returns_pv_op_sp_mv_of_the_last_period_in_order(opcua_mode, config):
    async with (EmulatorServer(config, port=0, time_scale=0) as srv,
                serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, history=600) as opc,
                Client(opc.url) as client):
        xv = await _variables(client, 2, "XV2")
        await xv["op"].write_value(ua.DataValue(ua.Variant(55.0, ua.VariantType.Double)))
        seen = []
        for _ in range(6):   # PV on its way after the step of OP: a new value every round
            await _ticks(srv.device, 1)
            seen.append(await xv["pv"].read_value())
        await asyncio.sleep(0.3)   # the history's own subscription publishes every 10 ms
        start, end = datetime.now(UTC) - timedelta(minutes=1), datetime.now(UTC)
        history = await xv["pv"].read_raw_history(start, end)
        values = [dv.Value.Value for dv in history]
        assert values[-6:] == seen
        stamps = [dv.SourceTimestamp for dv in history]
        assert stamps == sorted(stamps) and all(start <= t <= end for t in stamps)
        ops = [dv.Value.Value for dv in await xv["op"].read_raw_history(start, end)]
        assert ops[-1] == 55.0
        assert await (await _variables(client, 1, "FIC101"))["sp"].read_raw_history(start, end)
        assert (await xv["mv"].read_attribute(ua.AttributeIds.Historizing)).Value.Value is True
        with pytest.raises(ua.UaStatusCodeError) as err:   # only PV, OP, SP and MV keep a history
            await xv["kc"].read_raw_history(start, end)
        assert type(err.value).__name__ == "BadHistoryOperationUnsupported"


async def test_history_keeps_only_the_period(opcua_mode, config):
    async with (EmulatorServer(config, port=0, time_scale=0) as srv,
                serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, history=1.0) as opc,
                Client(opc.url) as client):
        xv = await _variables(client, 2, "XV2")
        await xv["op"].write_value(ua.DataValue(ua.Variant(55.0, ua.VariantType.Double)))
        await _ticks(srv.device, 3)
        await asyncio.sleep(1.5)
        cut = datetime.now(UTC) - timedelta(seconds=1.0)
        await _ticks(srv.device, 2)   # each new value drops what is older than the period
        await asyncio.sleep(0.3)
        history = await xv["pv"].read_raw_history(datetime.now(UTC) - timedelta(minutes=1), datetime.now(UTC))
    assert len(history) >= 2 and all(dv.SourceTimestamp >= cut for dv in history), history


async def test_without_history_nothing_is_historized(opcua_mode, config):
    async with (EmulatorServer(config, port=0, time_scale=0) as srv,
                serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0) as opc,
                Client(opc.url) as client):
        pv = (await _variables(client, 2, "XV2"))["pv"]
        assert (await pv.read_attribute(ua.AttributeIds.Historizing)).Value.Value is False
        with pytest.raises(ua.UaStatusCodeError) as err:
            await pv.read_raw_history(datetime.now(UTC) - timedelta(minutes=1), datetime.now(UTC))
        assert type(err.value).__name__ == "BadHistoryOperationUnsupported"


@pytest.mark.parametrize(("text", "seconds"), [("600", 600.0), ("90s", 90.0), ("10m", 600.0), ("10min", 600.0),
                                               ("1.5h", 5400.0)])
def test_history_durations(text, seconds):
    assert history_seconds(text) == seconds


@pytest.mark.parametrize("text", ["", "0", "10x", "-5m", "m"])
def test_a_history_duration_that_is_not_one_names_the_flag(text):
    with pytest.raises(HistoryError, match="--opcua-history"):
        history_seconds(text)


async def test_serve_opcua_history_answers_history_read_of_pv():
    started = datetime.now(UTC)
    proc, url, _ = start_serve("--opcua", "0", "--opcua-history", "10m")
    try:
        await asyncio.sleep(1.0)   # time-scale 10: ten simulated seconds, a tick every 10 ms
        async with Client(url) as client:
            pv = client.get_node("ns=2;s=Unit1.concentration_undershoot.pv")
            op = client.get_node("ns=2;s=Unit1.concentration_undershoot.op")
            await op.write_value(ua.DataValue(ua.Variant(61.5, ua.VariantType.Double)))
            await asyncio.sleep(2.5)   # the valve slips; PV follows after the plant's 10 s delay: 1 s here
            now = datetime.now(UTC)
            try:
                history = await pv.read_raw_history(now - timedelta(minutes=10), now)
            except ua.UaStatusCodeError as exc:   # the server's own log says why
                history = exc
    finally:
        err = stop(proc)
    assert not isinstance(history, Exception), f"HistoryRead refused: {history!r}; server log: {err[-3000:]}"
    assert "Traceback" not in err, err[-2000:]
    assert len(history) >= 5 and len({dv.Value.Value for dv in history}) >= 5
    # stamped with the time the device ran the tick (the first value's: before the address space was built,
    # however long that took on a loaded machine), not with when the OPC UA process sampled it
    assert all(started < dv.SourceTimestamp <= now for dv in history)


@pytest.mark.parametrize(("args", "message"), [
    (["--opcua-history", "10m"], "--opcua-history needs OPC UA"),
    (["--opcua", "0", "--opcua-history", "10x"], "--opcua-history '10x'"),
])
def test_serve_refuses_a_history_it_cannot_keep(args, message, capsys):
    assert main(["serve", "--port", "0", *args]) == 2
    assert message in capsys.readouterr().err
