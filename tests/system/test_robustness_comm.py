"""A scripted communication outage seen from a SCADA-like client: a training scenario (the real player and
emulator) silences the unit for 2 s of simulated time; a client polling meanwhile gets no answers inside
the window and answers again after it, and the scenario's next event is carried out."""

from __future__ import annotations

import asyncio
import struct
import textwrap

import pytest

from valve_emulator.clients.scenario import run_scenario
from valve_emulator.device.registers import address_of
from valve_emulator.scenario import parse_scenario

pytestmark = pytest.mark.usefixtures("no_task_leak")

SCENARIO = textwrap.dedent("""\
    device:
      plant: {num: [3.0], den: [10.0, 1.0], pv_range: [-10.0, 10.0]}
      device: {unit: 1, tick: 0.1}
    duration: 5
    time_scale: 2
    events:
      - {at: 1, event: comm, fault: no_response, duration: 2}
      - {at: 4, event: seize}
    """)


async def _poll(port: int, stop: asyncio.Event, seen: list[tuple[float, bool]]) -> None:
    """Read ``fault`` every 50 ms with a 150 ms timeout, on fresh connections after a silence."""
    loop = asyncio.get_running_loop()
    request = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, address_of("fault"), 1)
    reader = writer = None
    while not stop.is_set():
        if writer is None:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(request)
        try:
            answer = await asyncio.wait_for(reader.readexactly(11), 0.15)
            seen.append((loop.time(), answer[7:9] == b"\x03\x02"))
        except TimeoutError:
            seen.append((loop.time(), False))
            writer.close()                 # the unanswered request would stay in line: start afresh
            reader = writer = None
        except (asyncio.IncompleteReadError, ConnectionError):
            break                          # the server closed: the scenario is over (the checks below need it late)
        await asyncio.sleep(0.05)
    if writer is not None:
        writer.close()


async def test_a_scripted_outage_silences_the_unit_for_its_duration():
    scenario = parse_scenario(SCENARIO, source="outage.yaml")
    started, stop, seen = asyncio.Event(), asyncio.Event(), []
    servers = []

    def ready(srv):
        servers.append(srv)
        started.set()

    async def client():
        await started.wait()
        await _poll(servers[0].port, stop, seen)

    poller = asyncio.create_task(client())
    t0 = asyncio.get_running_loop().time()
    applied = await run_scenario(scenario, port=0, ready=ready)
    stop.set()
    await poller
    assert [a.event.kind for a in applied] == ["comm", "comm", "seize"]
    # wall time at time-scale 2: the outage lasts from 0.5 s to 1.5 s after the start (and the checks before)
    silent = [t - t0 for t, answered in seen if not answered]
    answered = [t - t0 for t, ok in seen if ok]
    assert len(silent) >= 3, seen
    assert max(silent) - min(silent) == pytest.approx(1.0, abs=0.35)
    assert any(t > max(silent) for t in answered) and any(t < min(silent) for t in answered)
