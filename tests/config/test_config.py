"""YAML configuration layer: valid files load into the expected objects; every error names file and key."""

from __future__ import annotations

import copy
import dataclasses
import re
import textwrap
from pathlib import Path

import pytest

from valve_emulator.config import (
    ConfigError,
    ControllerConfig,
    DeviceConfig,
    DisturbanceConfig,
    LoopConfig,
    PlantConfig,
    ServerConfig,
    SimulationConfig,
    ValveConfig,
    load_loop,
    load_server,
    loop_from_mapping,
    server_from_mapping,
)
from valve_emulator.config.schema import KEYS

DOCS = Path(__file__).resolve().parents[2] / "docs" / "config.md"

FULL = """\
name: concentration_undershoot
description: "the 2003 paper"
valve:
  model: kano
  seed_s: 5.0
  seed_j: 1.0
  rest_time: 0.25
  initial_direction: -1
  op0: 40
  characteristic: equal_percentage
  rangeability: 30.0
  ma_table: [[4, 0], [12, 40], [20, 100]]
plant:
  num: [3.0]
  den: [10.0, 1.0]
  delay: 10.0
  pv0: 1.5
  u0: 45.0
  pv_range: [-10.0, 10.0]
  units: "kg/m3"
  disturbance: {type: step, amplitude: -2.0, time: 100}
  noise: 0.05
controller:
  kc: 0.2
  ti: 10.0
  td: 1.0
  sp: 0.5
  sp_steps: [[10.0, 1.0], [20, 2]]
  bias: 45.0
  action: direct
  op_limits: [5.0, 95.0]
  mode: manual
simulation:
  dt: 0.05
  duration: 600.0
  seed: 7
device:
  unit: 12
  tick: 0.2
  word_order: CDAB
  instructor_writes: true
  instructor_hosts: ["127.0.0.1", "0:0:0:0:0:0:0:1"]
  read_only: false
"""

MINIMAL = "plant: {num: [1.0], den: [5.0, 1.0]}\n"


def write(tmp_path: Path, text: str, name: str = "x.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def error_of(fn, *args) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        fn(*args)
    return info.value


# --- valid files -------------------------------------------------------------------------------------

def test_full_example_loads_into_expected_objects(tmp_path):
    path = write(tmp_path, FULL)
    loop = load_loop(path)
    assert loop == LoopConfig(
        "concentration_undershoot", description="the 2003 paper", source=str(path),
        valve=ValveConfig(model="kano", S=5.0, J=2.0, rest_time=0.25, initial_direction=-1, op0=40.0,
                          characteristic="equal_percentage", rangeability=30.0,
                          ma_table=((4.0, 0.0), (12.0, 40.0), (20.0, 100.0)), seed_form=(5.0, 1.0)),
        plant=PlantConfig((3.0,), (10.0, 1.0), delay=10.0, pv0=1.5, u0=45.0, pv_range=(-10.0, 10.0),
                          units="kg/m3", disturbance=DisturbanceConfig(type="step", amplitude=-2.0, time=100.0),
                          noise=0.05),
        controller=ControllerConfig(0.2, ti=10.0, td=1.0, sp=0.5, sp_steps=((10.0, 1.0), (20.0, 2.0)),
                                    bias=45.0, action="direct", op_limits=(5.0, 95.0), mode="manual"),
        simulation=SimulationConfig(dt=0.05, duration=600.0, seed=7),
        device=DeviceConfig(unit=12, tick=0.2, word_order="CDAB", instructor_writes=True,
                            instructor_hosts=("127.0.0.1", "::1"), read_only=False),
    )
    # ints typed where floats are expected arrive as floats
    assert type(loop.valve.op0) is float and type(loop.controller.sp_steps[1][0]) is float


def test_seed_form_converts_once():
    loop = loop_from_mapping({"valve": {"seed_s": 3.0, "seed_j": 0.75}, "plant": {"integrator": {"gain": 1}}})
    assert (loop.valve.S, loop.valve.J, loop.valve.seed_form) == (3.0, 1.5, (3.0, 0.75))
    only_j = loop_from_mapping({"valve": {"seed_j": 1.0}, "plant": {"integrator": {"gain": 1}}})
    assert (only_j.valve.S, only_j.valve.J, only_j.valve.seed_form) == (0.0, 2.0, (0.0, 1.0))
    plain = loop_from_mapping({"valve": {"S": 5, "J": 2}, "plant": {"integrator": {"gain": 1}}})
    assert (plain.valve.S, plain.valve.J, plain.valve.seed_form) == (5.0, 2.0, None)


def test_defaults_of_a_minimal_file(tmp_path):
    loop = load_loop(write(tmp_path, MINIMAL, "level_loop.yaml"))
    assert loop.name == "level_loop" and loop.description == ""
    assert loop.valve == ValveConfig() and loop.valve.model == "kano" and loop.valve.rest_time == 0.5
    assert loop.valve.ma_table == ((4.0, 0.0), (20.0, 100.0))
    assert loop.plant.delay == 0.0 and loop.plant.u0 is None and loop.plant.pv_range == (-100.0, 100.0)
    assert loop.plant.disturbance == DisturbanceConfig(type="none")
    assert loop.controller is None
    assert loop.simulation == SimulationConfig(dt=0.1, duration=3000.0, seed=0)
    assert loop.device == DeviceConfig(unit=1, tick=0.1, word_order="ABCD")


def test_controller_sp_defaults_to_pv0_and_null_controller_is_absent():
    plant = {"fopdt": {"gain": 3, "tau": 10}, "pv0": 20.0}
    loop = loop_from_mapping({"plant": plant, "controller": {"kc": 0.2}})
    assert loop.controller.sp == 20.0 and loop.controller.ti is None and loop.plant.pv_range == (-80.0, 120.0)
    assert loop_from_mapping({"plant": plant, "controller": None}).controller is None


@pytest.mark.parametrize("plant, num, den, delay", [
    ({"fopdt": {"gain": 3.0, "tau": 10.0, "delay": 10.0}}, (3.0,), (10.0, 1.0), 10.0),
    ({"fopdt": {"gain": 2, "tau": 0}}, (2.0,), (1.0,), 0.0),
    ({"integrator": {"gain": 0.5, "delay": 1.5}}, (0.5,), (1.0, 0.0), 1.5),
    ({"num": [1, 2], "den": [1, 3, 2]}, (1.0, 2.0), (1.0, 3.0, 2.0), 0.0),
    ({"num": [0, 0, 4], "den": [2, 1]}, (0.0, 0.0, 4.0), (2.0, 1.0), 0.0),  # leading zeros: still proper
])
def test_plant_forms_expand_to_num_den_delay(plant, num, den, delay):
    p = loop_from_mapping({"plant": plant}).plant
    assert (p.num, p.den, p.delay) == (num, den, delay)


def test_load_server_accepts_a_single_loop_file(tmp_path):
    server = load_server(write(tmp_path, FULL))
    assert isinstance(server, ServerConfig) and len(server.loops) == 1
    assert server.loops[0].device.unit == 12 and server.device.unit is None
    assert server.device.word_order == "CDAB" and server.source.endswith("x.yaml")


MULTI = """\
device: {tick: 0.05, word_order: CDAB, instructor_writes: true}
loops:
  - unit: 3
    name: conc
    valve: {S: 5.0, J: 2.0}
    plant: {fopdt: {gain: 3.0, tau: 10.0, delay: 10.0}}
    controller: {kc: 0.2, ti: 10.0}
  - unit: 1
    plant: {integrator: {gain: 1.0}}
"""


def test_multi_loop_file(tmp_path):
    server = load_server(write(tmp_path, MULTI))
    assert server.device == DeviceConfig(unit=None, tick=0.05, word_order="CDAB", instructor_writes=True)
    assert [(lp.name, lp.device.unit) for lp in server.loops] == [("conc", 3), ("loop_001", 1)]
    assert all(lp.device == dataclasses.replace(server.device, unit=lp.device.unit) for lp in server.loops)
    assert server.loops[1].controller is None


FLEET = """\
loops:
  - {unit: 2, plant: {integrator: {gain: 1.0}}}
fleet:
  count: 30
  first_unit: 1
  seed: {seed}
  base:
    valve: {seed_s: 4.0, seed_j: 1.0}
    plant: {num: [2.0, 1.0], den: [10.0, 1.0], delay: 1.0}
  vary: {vary}
"""


def fleet(tmp_path, seed=0, vary="{S: [2.0, 6.0], J: [0.0, 3.0], gain: [0.5, 2.0], delay: [0.0, 5.0]}"):
    return load_server(write(tmp_path, FLEET.replace("{seed}", str(seed)).replace("{vary}", vary)))


def test_fleet_expansion_deterministic_and_within_ranges(tmp_path):
    a, b, c = fleet(tmp_path), fleet(tmp_path), fleet(tmp_path, seed=1)
    assert a == b and a.loops[1:] != c.loops[1:]
    generated = a.loops[1:]
    assert len(generated) == 30
    assert [lp.device.unit for lp in generated] == [1] + list(range(3, 32))  # unit 2 is taken by loops[0]
    assert generated[0].name == "fleet_001" and len({lp.name for lp in generated}) == 30
    for lp in generated:
        gain = lp.plant.num[0] / 2.0
        assert 2.0 <= lp.valve.S <= 6.0 and 0.0 <= lp.valve.J <= 3.0 and 0.0 <= lp.plant.delay <= 5.0
        assert 0.5 <= gain <= 2.0 and lp.plant.num[1] == pytest.approx(gain)  # every coefficient scaled
        assert lp.valve.seed_form is None and lp.plant.den == (10.0, 1.0)
    # the draws actually spread over the range
    assert max(lp.valve.S for lp in generated) - min(lp.valve.S for lp in generated) > 2.0
    # each quantity has its own stream: adding a vary key does not change the S draws
    only_s = fleet(tmp_path, vary="{S: [2.0, 6.0]}")
    assert [lp.valve.S for lp in only_s.loops[1:]] == [lp.valve.S for lp in generated]
    assert all(lp.valve.J == 2.0 and lp.plant.delay == 1.0 for lp in only_s.loops[1:])


def test_fleet_loops_equal_the_same_loops_built_with_every_check(tmp_path):
    # the fleet derives its loops without running the checks again (they are valid by construction); each
    # must equal, field for field, the loop dataclasses.replace builds from the base with every check run
    cfg = fleet(tmp_path)
    base = cfg.loops[1]
    for lp in cfg.loops[1:]:
        valve = dataclasses.replace(base.valve, S=lp.valve.S, J=lp.valve.J, seed_form=None)
        plant = dataclasses.replace(base.plant, num=lp.plant.num, delay=lp.plant.delay)
        device = dataclasses.replace(base.device, unit=lp.device.unit, block=lp.device.block)
        checked = dataclasses.replace(base, name=lp.name, valve=valve, plant=plant, device=device)
        assert lp == checked and type(lp) is LoopConfig


def test_a_fleet_whose_ranges_allow_a_bad_loop_is_refused_as_before(tmp_path):
    # a gain so large that the plant's coefficients overflow: a corner of the ranges is checked and refused
    with pytest.raises(ConfigError, match="finite"):
        fleet(tmp_path, vary="{gain: [1.0, 1.0e+308]}")


def test_fleet_without_vary_keeps_the_base(tmp_path):
    lp = fleet(tmp_path, vary="{}").loops[5]
    assert (lp.valve.S, lp.valve.J, lp.valve.seed_form, lp.plant.num) == (4.0, 2.0, (4.0, 1.0), (2.0, 1.0))


# --- errors ------------------------------------------------------------------------------------------

VALID_PLANT = "plant: {num: [1.0], den: [5.0, 1.0]}\n"
ERRORS = [
    # (file text, substrings the message must contain (after "<file>:"), expected line or None)
    ("valvee: {}\n" + VALID_PLANT, ["unknown key valvee", "allowed: name"], 1),
    ("valve:\n  Sj: 1\n" + VALID_PLANT, ["unknown key valve.Sj", "allowed: model, S, J"], 2),
    ("plant: {num: [1], den: [1, 1], gainn: 2}\n", ["unknown key plant.gainn"], 1),
    ("plant:\n  fopdt: {gain: 1, tau: 1, tua: 2}\n", ["unknown key plant.fopdt.tua"], 2),
    ("plant:\n  num: [1]\n  den: [1, 1]\n  disturbance: {type: step, amplitude: 1, std: 2}\n",
     ["unknown key plant.disturbance.std", "allowed: type, amplitude, time"], 4),
    (VALID_PLANT + "controller: {kc: 1, tii: 3}\n", ["unknown key controller.tii"], 2),
    (VALID_PLANT + "simulation:\n  dt: 0.1\n  durration: 5\n", ["unknown key simulation.durration"], 4),
    (VALID_PLANT + "device: {unit: 1, port: 502}\n", ["unknown key device.port"], 2),
    (VALID_PLANT + "simulation: {dt: fast}\n", ["simulation.dt must be a number, got 'fast' (text)"], 2),
    (VALID_PLANT + "simulation: {duration: 1e3}\n", ["simulation.duration must be a number", "1.0e+3"], 2),
    (VALID_PLANT + "valve: {S: true}\n", ["valve.S must be a number, got true (a boolean)"], 2),
    (VALID_PLANT + "simulation: {seed: 1.5}\n", ["simulation.seed must be an integer, got 1.5"], 2),
    (VALID_PLANT + "device: {read_only: 1}\n", ["device.read_only must be true or false, got 1"], 2),
    (VALID_PLANT + "valve: {S: .inf}\n", ["valve.S must be finite"], 2),
    ("plant:\n  num: [3.0]\n  den: [10.0, 1.0]\n  delay: -3\n", ["plant.delay must be >= 0, got -3"], 4),
    ("plant:\n  fopdt: {gain: 3, tau: 10, delay: -1}\n", ["plant.fopdt.delay must be >= 0, got -1"], 2),
    ("plant:\n  num: [1, 2, 3]\n  den: [1, 1]\n", ["plant.num has degree 2 > degree 1 of den", "proper"], 2),
    ("plant:\n  num: [1]\n  den: [0, 1]\n", ["plant.den[0] leading coefficient must be nonzero"], 3),
    ("plant:\n  num: [1, .nan]\n  den: [1, 1]\n", ["plant.num[1] must be finite"], 2),
    ("plant:\n  num: [0]\n  den: [1, 1]\n", ["plant.num must not be all zero"], 2),
    ("plant: {num: [1]}\n", ["missing key plant.den"], 1),
    ("plant: {num: [1], den: [1], fopdt: {gain: 1, tau: 1}}\n",
     ["plant.fopdt cannot be combined with plant.num"], 1),
    ("plant: {fopdt: {gain: 1, tau: 1}, delay: 2}\n", ["plant.delay is only for num/den"], 1),
    ("plant: {fopdt: {gain: 0, tau: 1}}\n", ["plant.fopdt.gain must be nonzero"], 1),
    ("plant: {pv0: 1}\n", ["plant must give the process as num + den"], 1),
    ("valve: {}\n", ["missing key plant"], None),
    ("plant:\n  num: [1]\n  den: [1, 1]\n  delay: 1.0e+6\n", ["plant.delay is rejected by the plant model"], 4),
    ("valve:\n  S: 5\n  seed_s: 5\n" + VALID_PLANT, ["valve.seed_s cannot be combined with valve.S"], 3),
    ("valve:\n  J: 2\n  seed_j: 1\n" + VALID_PLANT, ["valve.seed_j cannot be combined with valve.J"], 3),
    ("valve: {seed_s: -1}\n" + VALID_PLANT, ["valve.seed_s must be >= 0, got -1"], 1),
    (VALID_PLANT + "device:\n  word_order: BADC\n",
     ["device.word_order must be one of ABCD, CDAB, got 'BADC'"], 3),
    (VALID_PLANT + "device: {unit: 248}\n", ["device.unit must be in 1..247, got 248"], 2),
    (VALID_PLANT + "device:\n  instructor_hosts: [127.0.0.1, nohost]\n",
     ["device.instructor_hosts[1] must be an IP address, got 'nohost'"], 3),
    (VALID_PLANT + "controller:\n  kc: 1\n  sp_steps:\n    - [10, 1]\n    - [10, 2]\n",
     ["controller.sp_steps[1] times must be strictly increasing, got 10 after 10"], 6),
    (VALID_PLANT + "controller: {kc: 1, sp_steps: [[-1, 1]]}\n", ["controller.sp_steps[0][0] must be >= 0"], 2),
    (VALID_PLANT + "controller: {kc: 0}\n", ["controller.kc must be > 0, got 0"], 2),
    (VALID_PLANT + "controller: {ti: 3}\n", ["missing key controller.kc"], 2),
    (VALID_PLANT + "controller: {kc: 1, op_limits: [100, 0]}\n",
     ["controller.op_limits must be [lo, hi] with lo < hi"], 2),
    (VALID_PLANT + "controller: {kc: 1, action: forward}\n",
     ["controller.action must be one of reverse, direct"], 2),
    (VALID_PLANT + "valve:\n  ma_table:\n    - [4, 0]\n    - [12, 60]\n    - [20, 50]\n",
     ["valve.ma_table[2] % travel must be strictly monotone, got 50 after 60"], 6),
    (VALID_PLANT + "valve:\n  ma_table: [[4, 0], [4, 100]]\n",
     ["valve.ma_table[1] mA must be strictly increasing, got 4 after 4"], 3),
    (VALID_PLANT + "valve: {ma_table: [[4, 0]]}\n", ["valve.ma_table must have at least 2 item(s)"], 2),
    (VALID_PLANT + "valve: {model: stickyy}\n", ["valve.model must be one of choudhury, kano, he"], 2),
    (VALID_PLANT + "valve: {initial_direction: 0}\n", ["valve.initial_direction must be 1 or -1, got 0"], 2),
    (VALID_PLANT + "valve: {characteristic: linear, rangeability: 1}\n", ["valve.rangeability must be > 1"], 2),
    (VALID_PLANT + "valve: {actuator_lag: -2}\n", ["valve.actuator_lag must be >= 0, got -2"], 2),
    (VALID_PLANT + "valve:\n  actuator_lag: .inf\n", ["valve.actuator_lag must be finite"], 3),
    (VALID_PLANT + "valve: {flow_limits: [60, 40]}\n", ["valve.flow_limits must be [lo, hi] with lo < hi"], 2),
    (VALID_PLANT + "valve: {flow_limits: [50, 50]}\n", ["valve.flow_limits must be [lo, hi] with lo < hi"], 2),
    (VALID_PLANT + "valve: {flow_limits: [0, 120]}\n", ["valve.flow_limits[1] must be in 0..100 %, got 120"], 2),
    (VALID_PLANT + "valve: {flow_limits: [-5, 90]}\n", ["valve.flow_limits[0] must be in 0..100 %, got -5"], 2),
    (VALID_PLANT + "valve: {flow_limits: [10]}\n", ["valve.flow_limits must have exactly 2 items"], 2),
    ("plant: {num: [1], den: [1, 1], disturbance: {type: sine, amplitude: 1}}\n",
     ["missing key plant.disturbance.period"], 1),
    ("plant: {num: [1], den: [1, 1], disturbance: {type: ramp}}\n",
     ["plant.disturbance.type must be one of none, step, sine, random_walk"], 1),
    (VALID_PLANT + "simulation: {dt: 1.0, duration: 0.5}\n",
     ["simulation.duration must be >= dt (1), got 0.5"], 2),
    (VALID_PLANT + "name: 12\n", ["name must be text, got 12"], 2),
    ("valve:\n  S: 1\n  S: 2\n" + VALID_PLANT, ["duplicate key valve.S (first given on line 2)"], 3),
    ("valve:\n  S: [1, 2\n" + VALID_PLANT, ["YAML syntax error"], 3),
    ("valve: {S: 1}\n  bad: indent\n", ["YAML syntax error"], 2),
    ("valve: " + "[" * 5000 + "\n", ["YAML nested too deeply"], None),   # was a RecursionError
    ("", ["the file is empty"], None),
    ("- 1\n- 2\n", ["configuration must be a mapping, got list"], None),
    ("loops: []\n", ["loops makes this a multi-loop (server) file; load it with load_server"], 1),
]


@pytest.mark.parametrize("text, parts, line", ERRORS, ids=[str(i) for i in range(len(ERRORS))])
def test_errors_name_file_key_and_line(tmp_path, text, parts, line):
    path = write(tmp_path, text)
    err = error_of(load_loop, path)
    msg = str(err)
    prefix = f"{path}:{line}: " if line else f"{path}: "
    assert msg.startswith(prefix), msg
    for part in parts:
        assert part in msg, msg
    assert isinstance(err, ValueError)


SERVER_ERRORS = [
    ("loops:\n  - unit: 1\n    " + VALID_PLANT + "  - unit: 1\n    " + VALID_PLANT,
     ["loops[1].unit 1 is already used by loops[0] ('loop_001')"], 4),
    ("loops:\n  - {unit: 1, valve: {Sj: 2}, " + VALID_PLANT[:-1] + "}\n", ["unknown key loops[0].valve.Sj"], 2),
    ("loops:\n  - {unit: 1, device: {}, " + VALID_PLANT[:-1] + "}\n", ["unknown key loops[0].device"], 2),
    ("loops:\n  - " + VALID_PLANT, ["missing key loops[0].unit"], 2),
    ("loops:\n  - {unit: 0, " + VALID_PLANT[:-1] + "}\n", ["loops[0].unit must be in 1..247, got 0"], 2),
    ("loops: []\n", ["loops must have at least 1 item(s)"], 1),
    ("device: {unit: 3}\nloops:\n  - {unit: 1, " + VALID_PLANT[:-1] + "}\n",
     ["device.unit is not allowed in a multi-loop file"], 1),
    ("device:\n  word_order: abcd\nloops:\n  - {unit: 1, " + VALID_PLANT[:-1] + "}\n",
     ["device.word_order must be one of ABCD, CDAB, got 'abcd'"], 2),
    ("loops:\n  - {unit: 1, " + VALID_PLANT[:-1] + "}\nvalve: {}\n",
     ["unknown key valve (allowed: device, loops, fleet, opcua, tls)"], 3),
    ("fleet:\n  count: 5\n  bas: {}\n", ["unknown key fleet.bas"], 3),
    ("fleet:\n  count: 5\n  base: {" + VALID_PLANT[:-1] + "}\n  vary: {Q: [1, 2]}\n",
     ["unknown key fleet.vary.Q"], 4),
    ("fleet:\n  count: 5\n  base: {" + VALID_PLANT[:-1] + ", device: {}}\n", ["unknown key fleet.base.device"], 3),
    ("fleet:\n  count: 2\n  base: {valve: {S: -1}, " + VALID_PLANT[:-1] + "}\n",
     ["fleet.base.valve.S must be >= 0"], 3),
    ("fleet:\n  count: 5\n  base: {" + VALID_PLANT[:-1] + "}\n  vary: {S: [6, 2]}\n",
     ["fleet.vary.S must be [lo, hi] with lo <= hi"], 4),
    ("fleet:\n  count: 5\n  base: {" + VALID_PLANT[:-1] + "}\n  vary:\n    gain: [0, 2]\n",
     ["fleet.vary.gain[0] must be > 0, got 0"], 5),
    ("loops:\n  - {unit: 246, " + VALID_PLANT[:-1] + "}\nfleet:\n  count: 3\n  first_unit: 245\n  base: {"
     + VALID_PLANT[:-1] + "}\n", ["fleet.count must be <= 2 (units 245..247 not used by loops), got 3"], 4),
    ("fleet:\n  count: 2.0\n  base: {" + VALID_PLANT[:-1] + "}\n", ["fleet.count must be an integer"], 2),
]


@pytest.mark.parametrize("text, parts, line", SERVER_ERRORS, ids=[str(i) for i in range(len(SERVER_ERRORS))])
def test_server_errors_name_file_key_and_line(tmp_path, text, parts, line):
    path = write(tmp_path, text)
    msg = str(error_of(load_server, path))
    assert msg.startswith(f"{path}:{line}: "), msg
    for part in parts:
        assert part in msg, msg


def test_mapping_errors_name_source_and_key_without_line():
    msg = str(error_of(loop_from_mapping, {"plant": {"num": [1], "den": [1, 1], "delay": -3}}))
    assert msg == "<mapping>: plant.delay must be >= 0, got -3"
    msg = str(error_of(lambda: server_from_mapping({"fleet": {"count": 0, "base": {}}}, source="cli")))
    assert msg == "cli: fleet.count must be >= 1, got 0"


def test_missing_and_undecodable_files_are_config_errors(tmp_path):
    missing = tmp_path / "nope.yaml"
    assert str(error_of(load_loop, missing)).startswith(f"{missing}: cannot read the file")
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"name: \xff\xfe\n")
    assert str(error_of(load_loop, binary)) == f"{binary}: not UTF-8 text (byte 6)"


def test_error_carries_structured_fields(tmp_path):
    path = write(tmp_path, "plant:\n  num: [3.0]\n  den: [10.0, 1.0]\n  delay: -3\n")
    err = error_of(load_loop, path)
    assert (err.source, err.key, err.line) == (str(path), "plant.delay", 4)


# --- immutability ------------------------------------------------------------------------------------

def test_objects_are_frozen_and_replace_revalidates(tmp_path):
    loop = load_loop(write(tmp_path, FULL))
    with pytest.raises(dataclasses.FrozenInstanceError):
        loop.simulation.duration = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        loop.valve = ValveConfig()
    assert isinstance(loop.controller.sp_steps, tuple) and isinstance(loop.device.instructor_hosts, tuple)
    shorter = dataclasses.replace(loop, simulation=dataclasses.replace(loop.simulation, duration=60))
    assert shorter.simulation.duration == 60.0 and loop.simulation.duration == 600.0
    with pytest.raises(ConfigError, match=r"^duration must be > 0, got -1$"):
        dataclasses.replace(loop.simulation, duration=-1)
    with pytest.raises(ConfigError, match=r"S must be >= 0"):
        dataclasses.replace(loop.valve, S=-1.0)
    with pytest.raises(ConfigError, match=r"seed_form \(5, 1\) does not match S=4, J=2"):
        dataclasses.replace(loop.valve, S=4.0)  # the typed 2003-paper form would no longer describe the valve
    assert dataclasses.replace(loop.valve, S=4.0, seed_form=None).S == 4.0
    hash(loop)  # fully immutable, hence hashable


def test_failed_load_changes_nothing(tmp_path):
    good = load_loop(write(tmp_path, FULL, "good.yaml"))
    snapshot = copy.deepcopy(good)
    bad = FULL.replace("delay: 10.0", "delay: -10.0")
    with pytest.raises(ConfigError, match="plant.delay"):
        load_loop(write(tmp_path, bad, "bad.yaml"))
    assert good == snapshot and good.plant.delay == 10.0
    assert load_loop(tmp_path / "good.yaml") == good

    data = {"valve": {"seed_s": 5.0, "seed_j": 1.0}, "plant": {"num": [3.0], "den": [10.0, 1.0]},
            "controller": {"kc": 0.2}}
    before = copy.deepcopy(data)
    loop_from_mapping(data)
    data_bad = copy.deepcopy(data)
    data_bad["controller"]["kc"] = -1
    before_bad = copy.deepcopy(data_bad)
    with pytest.raises(ConfigError, match="controller.kc"):
        loop_from_mapping(data_bad)
    assert data == before and data_bad == before_bad  # the caller's mappings are never modified


# --- the documentation runs --------------------------------------------------------------------------

def _doc_examples() -> list[str]:
    return re.findall(r"```yaml\n(.*?)```", DOCS.read_text(encoding="utf-8"), flags=re.S)


def test_docs_examples_load(tmp_path):
    examples = _doc_examples()
    assert len(examples) >= 2
    single = load_loop(write(tmp_path, examples[0], "concentration_undershoot.yaml"))
    assert (single.valve.S, single.valve.J, single.valve.seed_form) == (5.0, 2.0, (5.0, 1.0))
    server = load_server(write(tmp_path, examples[1], "server.yaml"))
    assert len(server.loops) == 23 and server.loops[1].valve.J == 1.5
    assert [lp.device.unit for lp in server.loops[3:]] == list(range(10, 30))


def test_docs_document_every_key():
    rows = DOCS.read_text(encoding="utf-8")
    documented = set(re.findall(r"^\| `([A-Za-z_0-9]+)`", rows, flags=re.M))
    documented |= set(re.findall(r"`([a-z_]+)`, `", rows))  # the loops[i] row lists several keys
    every = {key for keys in KEYS.values() for key in keys}
    assert every - documented == set()


# --- connection hygiene keys ----------------------------------------------------------------

def test_connection_keys_default_and_load(tmp_path):
    d = DeviceConfig()
    assert (d.max_connections, d.idle_timeout, d.frame_timeout, d.error_rate) == (64, 60.0, 5.0, 100.0)
    text = VALID_PLANT + "device:\n  max_connections: 3\n  idle_timeout: 1.5\n  frame_timeout: 2\n  error_rate: 10\n"
    device = load_loop(write(tmp_path, text)).device
    assert (device.max_connections, device.idle_timeout, device.frame_timeout, device.error_rate) == (3, 1.5, 2.0, 10.0)
    server = load_server(write(tmp_path, "device: {max_connections: 7, frame_timeout: 0.25}\nloops:\n  - {unit: 1, "
                                         + VALID_PLANT[:-1] + "}\n", "s.yaml"))
    assert server.device.max_connections == 7 and server.loops[0].device.frame_timeout == 0.25


@pytest.mark.parametrize("text, parts, line", [
    (VALID_PLANT + "device:\n  max_connections: 0\n", ["device.max_connections must be in 1..65535, got 0"], 3),
    (VALID_PLANT + "device:\n  max_connections: 1.0e+2\n", ["device.max_connections must be an integer"], 3),
    (VALID_PLANT + "device:\n  max_connections: 70000\n", ["device.max_connections must be in 1..65535"], 3),
    (VALID_PLANT + "device: {idle_timeout: 0}\n", ["device.idle_timeout must be > 0, got 0"], 2),
    (VALID_PLANT + "device: {idle_timeout: .inf}\n", ["device.idle_timeout must be finite"], 2),
    (VALID_PLANT + "device: {frame_timeout: -1}\n", ["device.frame_timeout must be > 0, got -1"], 2),
    (VALID_PLANT + "device: {frame_timeout: soon}\n", ["device.frame_timeout must be a number, got 'soon'"], 2),
    (VALID_PLANT + "device: {error_rate: 0}\n", ["device.error_rate must be > 0, got 0"], 2),
    ("device: {max_connections: true}\nloops:\n  - {unit: 1, " + VALID_PLANT[:-1] + "}\n",
     ["device.max_connections must be an integer, got true"], 1),
])
def test_connection_key_errors_name_file_key_and_line(tmp_path, text, parts, line):
    err = error_of(load_server, write(tmp_path, text))
    for part in parts:
        assert part in str(err)
    assert err.line == line
