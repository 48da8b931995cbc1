"""The config writer: what it writes, the loader reads back to an equal config (every key, every section)."""

import dataclasses
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from valve_emulator.config import (
    ControllerConfig,
    DeviceConfig,
    DisturbanceConfig,
    LoopConfig,
    PlantConfig,
    SimulationConfig,
    ValveConfig,
    dump_loop,
    load_loop,
    write_loop,
)

CONFIGS = sorted((Path(__file__).parents[2] / "configs" / "table1").glob("*.yaml"))


def round_trip(cfg: LoopConfig, tmp_path: Path, header=()) -> LoopConfig:
    path = tmp_path / "loop.yaml"
    write_loop(cfg, path, header=header)
    return dataclasses.replace(load_loop(path), source=cfg.source)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_every_example_config_round_trips(path, tmp_path):
    cfg = load_loop(path)
    assert round_trip(cfg, tmp_path) == cfg


def full_loop(disturbance: DisturbanceConfig, controller: ControllerConfig | None) -> LoopConfig:
    """A loop that sets every optional key away from its default."""
    return LoopConfig(
        "every_key", description="all: keys; set 'away' # from defaults",
        valve=ValveConfig(model="he", S=4.5, J=1.25, rest_time=0.3, initial_direction=-1, op0=37.5,
                          actuator_lag=2.5, characteristic="equal_percentage", rangeability=30.0,
                          flow_limits=(12.5, 80.0),
                          ma_table=((4.0, 100.0), (20.0, 0.0)), op_range=(4000.0, 27648.0)),
        plant=PlantConfig((0.5, 2.0), (12.0, 7.0, 1.0), delay=3.3, pv0=-12.5, u0=41.0, pv_range=(-50.0, 25.0),
                          units="kg/m³", disturbance=disturbance, noise=0.05, alarms=(-40.0, 10.0)),
        controller=controller,
        simulation=SimulationConfig(dt=0.2, duration=1234.4, seed=7),
        device=DeviceConfig(unit=17, tick=0.05, word_order="CDAB", instructor_writes=True,
                            instructor_hosts=("127.0.0.1", "::1"), read_only=True, max_connections=5,
                            idle_timeout=12.5, frame_timeout=1.5, error_rate=7.0))


@pytest.mark.parametrize("disturbance", [
    DisturbanceConfig(), DisturbanceConfig(type="step", amplitude=-3.0, time=120.0),
    DisturbanceConfig(type="sine", amplitude=2.0, period=60.0, phase=0.5),
    DisturbanceConfig(type="random_walk", std=0.01)], ids=lambda d: d.type)
@pytest.mark.parametrize("controller", [
    None, ControllerConfig(0.4, ti=None, td=2.0, sp=1.5, sp_steps=((10.0, 2.0), (20.5, -1.0)), bias=30.0,
                           action="direct", op_limits=(5.0, 95.0), mode="manual")], ids=["open", "pid"])
def test_every_key_round_trips(disturbance, controller, tmp_path):
    cfg = full_loop(disturbance, controller)
    assert round_trip(cfg, tmp_path) == cfg


def test_the_header_is_comments_before_the_keys(tmp_path):
    cfg = load_loop(CONFIGS[0])
    text = dump_loop(cfg, header=["where: the numbers came from", "", "second line"])
    lines = text.splitlines()
    assert lines[:3] == ["# where: the numbers came from", "#", "# second line"]
    assert lines[3].startswith("name:")
    assert round_trip(cfg, tmp_path, header="one\ntwo") == cfg


def test_the_seed_paper_form_is_kept_as_typed(tmp_path):
    cfg = next(load_loop(p) for p in CONFIGS if load_loop(p).valve.seed_form is not None)
    text = dump_loop(cfg)
    assert "seed_s:" in text and "\n  S:" not in text
    assert round_trip(cfg, tmp_path).valve.seed_form == cfg.valve.seed_form


finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(gain=finite.filter(lambda x: x != 0.0), tau=st.floats(min_value=1e-9, max_value=1e9),
       pv0=finite, noise=st.floats(min_value=0.0, max_value=1e9), S=st.floats(min_value=0.0, max_value=1e3))
def test_any_float_reads_back_exactly(gain, tau, pv0, noise, S, tmp_path_factory):
    """PyYAML writes the shortest repr of a float and always with a dot, so 1e3-like text never comes back as
    a string and no digit is lost."""
    cfg = LoopConfig("floats", valve=ValveConfig(S=S, J=S / 3.0),
                     plant=PlantConfig((gain,), (tau, 1.0), pv0=pv0, noise=noise))
    assert round_trip(cfg, tmp_path_factory.mktemp("f")) == cfg
