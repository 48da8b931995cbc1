"""Hostile input on the OPC UA port and failed TLS handshakes on both secure ports, while the device ticks in
real time: no crash, ticks on schedule, Modbus and a well-behaved OPC UA client answered correctly after.
The same generator runs 10^5 messages in ``bench/bench_opcua.py``; here a reduced size."""

import asyncio
import multiprocessing
import ssl
import time
from concurrent.futures import ProcessPoolExecutor

import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from valve_emulator.device.certs import modbus_certificate
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.tls import server_context
from valve_emulator.opcua import NAMESPACE

from .hostile import KINDS, attack
from .modes import serve_opcua

MESSAGES = 1600     # 200 of each kind


async def test_malformed_opcua_and_failed_handshakes_harm_nothing(opcua_mode, config, tmp_path):
    modbus_certificate(tmp_path, "server", server=True)
    async with EmulatorServer(config, port=0, time_scale=1.0) as srv:
        await srv.open_tls(server_context(tmp_path / "server.pem", tmp_path / "server-key.pem", tmp_path / "ca.pem"),
                           port=0)
        async with serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0) as opc:
            ticks0, overruns0, t0 = srv.device.ticks, srv.device.overruns, time.monotonic()
            loop = asyncio.get_running_loop()
            # The attacker is another process, as it would be: in a thread of this one its four sender threads
            # would take the GIL from the event loop, and the tick would measure the test, not the server.
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as attacker:
                sent = await loop.run_in_executor(attacker, attack, "127.0.0.1", opc.port, opc.url, MESSAGES)
            handshakes = await loop.run_in_executor(None, _bad_handshakes, srv.tls_port, 50)
            # count the ticks over at least 3 s from the attack's start: over a shorter window one tick more
            # or less than the clock allows is already more than the 10 % the rate may deviate
            await asyncio.sleep(max(0.0, t0 + 3.0 - time.monotonic()))
            elapsed, ticks = time.monotonic() - t0, srv.device.ticks - ticks0
            assert all(sent[k] == MESSAGES // len(KINDS) for k in KINDS)
            assert sent["closed_by_server"] >= 0.9 * MESSAGES      # the server ends a broken connection itself
            assert all(handshakes) and srv.tls_sessions == 0
            # the tick kept its schedule: 10 ± 1 ticks a second over the attack, no tick a period late
            assert 9.0 <= ticks / elapsed <= 11.0, (ticks, elapsed)
            assert srv.device.overruns == overruns0 and srv.device.error is None
            # normal clients are answered correctly afterwards
            async with Client(opc.url) as client:
                ns = await client.get_namespace_index(NAMESPACE)
                pv = await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit2", f"{ns}:XV2",
                                                           f"{ns}:op"])
                await pv.write_value(ua.DataValue(ua.Variant(44.0, ua.VariantType.Double)))
                assert await pv.read_value() == pytest.approx(44.0)
            async with AsyncModbusTcpClient("127.0.0.1", port=srv.port) as mb:
                rr = await mb.read_holding_registers(0, count=1, device_id=2)
                assert not rr.isError() and rr.registers[0] == 4400


def _bad_handshakes(port: int, count: int) -> list[bool]:
    """``count`` TLS clients without a certificate (from another thread, as an attacker would be another
    process): True for each one the server refused (no answer to a Modbus request)."""
    import socket

    ctx = ssl.create_default_context()
    ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
    refused = []
    for _ in range(count):
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=10) as raw, \
                    ctx.wrap_socket(raw) as sock:
                sock.sendall(bytes.fromhex("000100000006010300000001"))
                refused.append(sock.recv(100) == b"")
        except (ssl.SSLError, ConnectionError):
            refused.append(True)
    return refused
