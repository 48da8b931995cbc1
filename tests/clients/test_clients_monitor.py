"""The instructor's live view: what it prints for a running emulator, once and over time, on any device."""

from __future__ import annotations

import io
import math

import pytest

from valve_emulator.clients._modbus import Link
from valve_emulator.clients.monitor import (
    Sample,
    build_parser,
    main,
    monitor,
    options_from_args,
    render_row,
    valve_state,
)
from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import Status, address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

LOOP = {"valve": {"S": 2.0, "J": 1.0}, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]},
        "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0, "sp_steps": [[1.0, 1.0]]}}


def config():
    return server_from_mapping({"device": {"tick": 0.1, "instructor_writes": True},
                                "loops": [{"unit": 1, **LOOP}]})


async def show(port: int, *flags: str, tty: bool = False) -> tuple[int, str]:
    opts = options_from_args(build_parser().parse_args(["--port", str(port), *flags]), tty=tty)
    out = io.StringIO()
    n = await monitor(opts, out=out)
    return n, out.getvalue()


async def test_once_shows_values_state_and_the_instructor_faults():
    async with EmulatorServer(config(), time_scale=0) as srv:
        link = Link("127.0.0.1", srv.port, 1)
        await link.connect()
        try:
            await link.write(address_of("load"), [150, 0, 1])          # load 1.5 %, no noise, seized
        finally:
            link.close()
        srv.device.advance(12)                        # samples 0..11: past the set-point step at 1 s, t = 1.1 s
        bank = srv.device.bank
        op, pv = f"{bank.op[0]:.2f}", f"{bank.pv[0]:.3f}"
        n, text = await show(srv.port, "--once", tty=True)            # redraw mode
        assert n == 1 and text.startswith("\x1b[H\x1b[J")
        assert "t = 1.1 s" in text and "SP     1.000" in text and f"PV {pv:>9s}" in text and f"OP {op:>7s} %" in text
        assert "valve SEIZED" in text
        assert "instructor: S 2 %   J 1 %   load 1.5 % flow   noise 0 % of range   fault 1" in text
        n, plain = await show(srv.port, "--once", "--pv-range", "-10", "10", "--width", "21")
        assert "\x1b" not in plain and n == 1
        row = plain.splitlines()[-1]
        assert row.split()[:6] == ["1.1", "1.000", pv, op, "49.50", "SEIZED"]
        assert row.endswith("|          ms         |")      # MV (over OP and PV) mid-scale, SP just above


async def test_plain_mode_scrolls_one_row_per_sample_and_tells_stuck_from_moving():
    async with EmulatorServer(config(), time_scale=20) as srv:
        n, text = await show(srv.port, "--duration", "0.6", "--period", "0.05", "--width", "30")
    rows = [ln for ln in text.splitlines() if ln.strip()[:1].isdigit()]
    assert len(rows) == n >= 8
    times = [float(r.split()[0]) for r in rows]
    assert times == sorted(times) and times[-1] > 5.0
    assert {r.split()[5] for r in rows} <= {"stuck", "moving"} and "stuck" in text
    assert text.count("t [s]") >= 1 and "valve monitor -- 127.0.0.1" in text


async def test_any_device_without_status_word_gets_the_state_from_mv():
    async with EmulatorServer(config(), time_scale=0) as srv:
        srv.device.advance(3)
        n, text = await show(srv.port, "--once", "--no-extras", "--sp", "0.5", "--time", "none",
                             "--op", "holding:0:uint16:100", "--mv", "holding:2:uint16:100")
    row = text.splitlines()[-1]
    assert row.split()[1:6] == ["0.500", "0.000", "50.00", "49.50", "?"]   # one sample: no MV change seen yet


def test_valve_state_and_trend_row():
    assert valve_state(int(Status.STUCK | Status.SEIZED), 1.0, None) == "SEIZED"
    assert valve_state(int(Status.MOVING), 1.0, None) == "moving"
    assert valve_state(None, 40.0, 40.0) == "stuck" and valve_state(None, 41.0, 40.0) == "moving"
    assert valve_state(None, math.nan, 40.0) == "?"
    s = Sample(t=12.0, sp=5.0, pv=10.0, op=100.0, mv=0.0, state="moving", extras={})
    row = render_row(s, width=11, pv_range=(0.0, 10.0))
    assert row.endswith("|m    s    o|")          # OP at 100 % is drawn over PV at the top of its axis
    assert render_row(Sample(1.0, math.nan, 0.0, 50.0, 50.0, "stuck", {}), width=11,
                      pv_range=(0.0, 10.0)).endswith("|p    m     |")


def test_bad_flags(capsys):
    assert main(["--width", "3"]) == 2
    assert "--width must be >= 10" in capsys.readouterr().err
    assert main(["--pv-range", "5", "1"]) == 2
