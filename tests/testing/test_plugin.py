"""The pytest plugin: fixtures in sync and async tests, the marker, the ini options, the factory."""

from __future__ import annotations

import tomllib
from pathlib import Path

from kit_helpers import PLUGIN

ROOT = Path(__file__).resolve().parents[2]


def test_pyproject_registers_the_plugin_as_a_pytest11_entry_point():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert PLUGIN in project["entry-points"]["pytest11"].values()


def test_fixtures_marker_and_ini_options_in_sync_and_async_tests(pytester, run_pytest):
    pytester.makeini("""
        [pytest]
        asyncio_mode = auto
        asyncio_default_fixture_loop_scope = function
        valve_emulator_config = devices/slow.yaml
        valve_emulator_clock = manual
    """)
    pytester.mkdir("devices")
    (pytester.path / "devices" / "slow.yaml").write_text(
        "device: {tick: 0.5}\nloops:\n  - unit: 4\n    plant: {num: [1.0], den: [3.0, 1.0]}\n")
    pytester.makepyfile(test_kit="""
        import asyncio
        import pytest

        def test_sync_flavour_from_the_ini_file(valve_emulator):
            assert valve_emulator.units == (4,) and valve_emulator.dt == 0.5
            assert valve_emulator.advance(10.0) == 20          # returns at once with the tick count

        async def test_async_flavour_runs_in_the_tests_loop(valve_emulator):
            assert await valve_emulator.advance(10.0) == 20
            assert valve_emulator.server.device is valve_emulator.device
            assert not [t for t in asyncio.all_tasks() if t.get_name() == "valve-emulator-tick"]   # manual clock

        @pytest.mark.valve_emulator(config=None, clock="real", time_scale=100.0)
        def test_the_marker_wins_over_the_ini(valve_emulator):
            assert valve_emulator.units == (1,) and valve_emulator.clock == "real"
            assert valve_emulator.advance(1.0) >= 10

        def test_the_factory_makes_several(valve_emulator_factory):
            a, b = valve_emulator_factory(), valve_emulator_factory(config=None)
            a.advance(5.0)
            assert (a.ticks, b.ticks, a.units, b.units) == (10, 0, (4,), (1,)) and a.port != b.port

        async def test_the_async_factory(valve_emulator_factory):
            a = await valve_emulator_factory()
            await a.advance(1.0)
            assert a.ticks == 2

        @pytest.mark.valve_emulator(clock="sideways")
        def test_a_bad_setting_is_an_error(valve_emulator):
            pass
    """)
    result = run_pytest("-q")
    result.assert_outcomes(passed=5, errors=1)
    result.stdout.fnmatch_lines(["*clock must be one of manual, real*"])
