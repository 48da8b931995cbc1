"""The OPC UA server in a process of its own: the device's checks decide writes, the tick's work does not grow
with subscribers, and the death of the OPC UA process is reported and stops ``serve`` cleanly."""

import asyncio
import logging
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
from asyncua import Client, ua

from valve_emulator.device.registers import RegisterAccessError, RegisterValueError, encode_write
from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua import NAMESPACE, OpcUaProcess
from valve_emulator.opcua.server import VARIABLES

from .test_opcua_interop import OPCUA_LINE

_VAR = {v.name: v for v in VARIABLES}


async def _node(client, unit, loop, var):
    ns = await client.get_namespace_index(NAMESPACE)
    return client.get_node(f"ns={ns};s=Unit{unit}.{loop}.{var}")


@pytest.mark.parametrize(("unit", "index", "loop", "var", "value", "refusal", "status"), [
    (1, 0, "FIC101", "sp", 80.0, RegisterValueError, "BadOutOfRange"),     # beyond the PV range 0..50
    (1, 0, "FIC101", "op", 40.0, RegisterAccessError, "BadNotWritable"),   # OP while the loop is in auto
])
async def test_a_write_the_device_refuses_is_refused_over_opcua_for_the_same_reason_and_changes_nothing(
        config, unit, index, loop, var, value, refusal, status):
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            OpcUaProcess(srv.device, loops=config.loops, port=0) as opc:
        device, reg = srv.device, _VAR[var].write
        with pytest.raises(refusal):   # the device's own verdict on the same write
            device.write(index, reg.address, encode_write(reg, value, device.scaling, index))
        image = bytes(device.image)
        async with Client(opc.url) as client:
            node = await _node(client, unit, loop, var)
            before = await node.read_value()
            with pytest.raises(ua.UaStatusCodeError) as err:
                await node.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.Double)))
            assert type(err.value).__name__ == status
            assert await node.read_value() == before
        assert bytes(device.image) == image and not device._pending
        assert (await opc.counters()).refused == 1


async def test_the_tick_copies_the_image_once_however_many_clients_subscribe(config):
    """Counted, not timed: each tick publishes the image once, and nothing else in the tick knows of OPC UA."""
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            OpcUaProcess(srv.device, loops=config.loops, port=0) as opc:
        device = srv.device
        assert device.on_tick == [] and len(device.image_listeners) == 1

        def copies_per_tick(ticks=5):
            before = opc.publisher.copies
            for _ in range(ticks):
                device.advance(1)
            return (opc.publisher.copies - before) / ticks

        alone = copies_per_tick()
        clients = [Client(opc.url) for _ in range(3)]
        for client in clients:
            await client.connect()
        try:
            for client in clients:
                sub = await client.create_subscription(20, None)
                nodes = [await _node(client, u, lp, v) for u, lp in ((1, "FIC101"), (2, "XV2"))
                         for v in ("pv", "op", "sp", "mv", "time")]
                await sub.subscribe_data_change(nodes)
            await asyncio.sleep(0.3)
            assert (alone, copies_per_tick()) == (1.0, 1.0)
            await asyncio.sleep(0.3)
            assert (await opc.counters()).notifications > 0   # the subscriptions were fed, by the other process
        finally:
            for client in clients:
                await client.disconnect()


async def test_a_killed_opcua_process_is_reported_and_the_device_goes_on(config, caplog):
    caplog.set_level(logging.ERROR, logger="valve_emulator.opcua.process")
    ended = asyncio.Event()
    codes = []

    def on_exit(code):
        codes.append(code)
        ended.set()

    async with EmulatorServer(config, port=0, time_scale=10.0) as srv:
        opc = OpcUaProcess(srv.device, loops=config.loops, port=0, on_exit=on_exit)
        await opc.start()
        try:
            os.kill(opc.process.pid, signal.SIGKILL)
            await asyncio.wait_for(ended.wait(), 10)
            ticks = srv.device.ticks
            await srv.device.wait_for_tick(ticks + 3)   # the device ticks on
        finally:
            await opc.stop()
    assert codes == [-signal.SIGKILL] and opc.exit_code == -signal.SIGKILL
    assert any("ended unexpectedly" in r.getMessage() for r in caplog.records)


def _serve_with_opcua(*args: str, **popen) -> tuple[subprocess.Popen, psutil.Process]:
    """``serve --port 0 --opcua 0 ARGS`` started and read up to its OPC UA line; (the process, its OPC UA process)."""
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--port", "0", "--opcua", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)
    lines: list[str] = []
    while not any(OPCUA_LINE.search(line) for line in lines):
        line = proc.stdout.readline()
        if not line:
            proc.kill()
            raise AssertionError(proc.communicate()[1][-2000:])
        lines.append(line)
    [child] = [p for p in psutil.Process(proc.pid).children() if "valve_emulator.opcua" in " ".join(p.cmdline())]
    return proc, child


def test_serve_stops_cleanly_with_status_1_when_its_opcua_process_dies(tmp_path):
    """The recording is closed as at Ctrl-C: every row written so far is there."""
    record = tmp_path / "rec.csv"
    proc, child = _serve_with_opcua("--time-scale", "10", "--record", str(record))
    try:
        deadline = time.monotonic() + 30
        while not (record.exists() and record.read_text().count("\n") > 3):   # a few rows recorded
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.2)
        child.kill()
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    assert "the OPC UA process ended unexpectedly" in err and "Traceback" not in err
    rows = record.read_text().splitlines()
    assert rows[0].startswith("t,") and len(rows) > 4 and rows[-1].count(",") == rows[0].count(",")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_to_the_whole_process_group_stops_serve_and_its_opcua_process_quietly(sig):
    """Ctrl-C in a terminal (and a service manager's SIGTERM) reaches every process of the group: the device
    stops its OPC UA process itself, so the answer is the usual "stopped", status 0, no traceback from either."""
    proc, child = _serve_with_opcua(start_new_session=True)
    try:
        os.killpg(proc.pid, sig)
        out, err = proc.communicate(timeout=30)
        child.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert "stopped" in out + err and "Traceback" not in err and "KeyboardInterrupt" not in err, err[-2000:]
