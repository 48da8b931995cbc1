"""Plant-size fleets: addressing beyond 247 loops, and one array-stepped bank == every loop alone."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.config import ConfigError, ServerConfig, server_from_mapping
from valve_emulator.config.schema import MAX_BLOCKS
from valve_emulator.device.registers import MAX_BLOCKS as MAP_MAX_BLOCKS
from valve_emulator.simulation.loop import LoopBank

DOCS = Path(__file__).resolve().parents[2] / "docs" / "config.md"
BASE = {"valve": {"S": 4.0, "J": 1.0}, "plant": {"fopdt": {"gain": 1.0, "tau": 15.0, "delay": 2.0}},
        "controller": {"kc": 0.5, "ti": 15.0}}
VARY = {"S": [2.0, 6.0], "J": [0.0, 3.0], "gain": [0.5, 2.0], "delay": [0.0, 5.0]}


def fleet(count, per_unit=1, *, loops=(), first_unit=1, vary=VARY, base=BASE):
    mapping = {"device": {"tick": 0.1}, "fleet": {"count": count, "loops_per_unit": per_unit, "seed": 3,
                                                  "first_unit": first_unit, "base": base, "vary": vary}}
    if loops:
        mapping["loops"] = list(loops)
    return server_from_mapping(mapping)


# --- addressing ------------------------------------------------------------------------------------------

def test_a_fleet_beyond_247_loops_fills_blocks_of_the_lowest_free_units():
    cfg = fleet(1000, 300, loops=[{"unit": 2, "plant": {"fopdt": {"gain": 1.0, "tau": 5.0}}}])
    generated = cfg.loops[1:]
    assert len(generated) == 1000
    where = [(lp.device.unit, lp.device.block) for lp in generated]
    # unit 2 belongs to loops[0]: the fleet takes 1, 3, 4, 5 with 300, 300, 300 and 100 loops
    assert where[:2] == [(1, 0), (1, 1)] and where[299:302] == [(1, 299), (3, 0), (3, 1)]
    assert where[-1] == (5, 99) and len(set(where)) == 1000
    assert generated[0].name == "fleet_001_0000" and generated[-1].name == "fleet_005_0099"
    assert cfg.loops[0].device.block == 0


def test_loops_per_unit_moves_loops_but_never_changes_their_parameters():
    one, many = fleet(200, 1), fleet(200, 64)
    params = lambda cfg: [(lp.valve, lp.plant, lp.controller) for lp in cfg.loops]  # noqa: E731
    assert params(one) == params(many)
    assert [lp.device.unit for lp in one.loops] == list(range(1, 201))
    assert {lp.device.unit for lp in many.loops} == {1, 2, 3, 4}


@pytest.mark.parametrize("count, per_unit, first_unit, words", [
    (248, 1, 1, ["fleet.count must be <= 247", "fleet.loops_per_unit"]),
    (4001, 20, 48, ["fleet.count must be <= 4000", "units 48..247", "loops_per_unit 20", "got 4001"]),
    (10, 0, 1, ["fleet.loops_per_unit must be in 1..2048, got 0"]),
    (10, 2049, 1, ["fleet.loops_per_unit must be in 1..2048, got 2049"]),
])
def test_fleet_size_and_addressing_errors_name_the_key(count, per_unit, first_unit, words):
    with pytest.raises(ConfigError) as err:
        fleet(count, per_unit, first_unit=first_unit, vary={})
    for word in words:
        assert word in str(err.value)


def test_server_config_refuses_shared_addresses_and_gaps_in_a_units_blocks():
    cfg = fleet(4, 4, vary={})
    lp = cfg.loops
    with pytest.raises(ConfigError, match=r"loops\[1\]\.unit 1 is already used by loops\[0\]"):
        ServerConfig(cfg.device, (lp[0], dataclasses.replace(lp[1], device=lp[0].device)))
    with pytest.raises(ConfigError, match=r"loops\[2\]\.unit 1 block 1 is already used by loops\[1\]"):
        ServerConfig(cfg.device, (lp[0], lp[1], dataclasses.replace(lp[2], device=lp[1].device)))
    with pytest.raises(ConfigError, match="unit 1 has block 3 but no block 2"):
        ServerConfig(cfg.device, (lp[0], lp[1], lp[3]))
    with pytest.raises(ConfigError, match=r"block must be in 0\.\.2047"):
        dataclasses.replace(lp[0].device, block=MAX_BLOCKS)
    assert MAX_BLOCKS == MAP_MAX_BLOCKS   # config and register map agree on the address space


def test_the_documented_10000_loop_example_loads_where_the_docs_say():
    text = DOCS.read_text(encoding="utf-8")
    example = next(e for e in re.findall(r"```yaml\n(.*?)```", text, flags=re.S) if "loops_per_unit" in e)
    import yaml

    cfg = server_from_mapping(yaml.safe_load(example))
    assert len(cfg.loops) == 10_000 and {lp.device.unit for lp in cfg.loops} == set(range(1, 101))
    loop = cfg.loops[4321]
    assert (loop.device.unit, loop.device.block) == (44, 21)
    assert "loop k = 4,321 (counting from 0) is unit 44, block 21 (`pv` at" in text and 32 * 21 + 4 == 676


# --- one bank of many == each loop alone ------------------------------------------------------------------

def mixed_fleet() -> ServerConfig:
    """Explicit loops of every kind (models, open loop, manual, direct, integrating, noise, disturbance,
    set-point steps) next to a generated fleet with varied S, J, gain and delay in blocks."""
    loops = [
        {"unit": 200, "valve": {"model": "choudhury", "S": 3.0, "J": 1.0},
         "plant": {"num": [2.0, 1.0], "den": [20.0, 6.0, 1.0], "delay": 0.35, "noise": 0.05},
         "controller": {"kc": 0.8, "ti": 12.0, "td": 0.5, "sp_steps": [[1.0, 2.0], [7.5, -1.0]]},
         "simulation": {"seed": 4}},
        {"unit": 201, "valve": {"model": "he", "S": 4.0, "J": 2.0, "characteristic": "equal_percentage"},
         "plant": {"integrator": {"gain": 0.05, "delay": 1.0}, "pv0": 50.0,
                   "disturbance": {"type": "sine", "amplitude": 3.0, "period": 9.0}},
         "controller": {"kc": 2.0, "ti": 30.0, "action": "direct", "sp_steps": [[3.0, 52.0]]}},
        {"unit": 202, "valve": {"S": 6.0, "J": 3.0, "op0": 40.0, "characteristic": "quick_opening"},
         "plant": {"fopdt": {"gain": 2.0, "tau": 5.0, "delay": 0.25},
                   "disturbance": {"type": "random_walk", "std": 0.5}, "noise": 0.1},
         "simulation": {"seed": 9}},
        {"unit": 203, "valve": {"S": 2.0, "J": 0.5}, "plant": {"fopdt": {"gain": 1.0, "tau": 8.0}},
         "controller": {"kc": 0.5, "ti": 8.0, "mode": "manual", "bias": 45.0}},
    ]
    base = dict(BASE, controller={"kc": 0.5, "ti": 15.0, "sp_steps": [[2.0, 1.5]]})
    return fleet(60, 16, loops=loops, base=base)


def test_fleet_bank_matches_every_loop_stepped_alone_exactly():
    cfg = mixed_fleet()
    bank = LoopBank(cfg.loops, dt=cfg.device.tick)
    alone = [LoopBank([lp], dt=cfg.device.tick) for lp in cfg.loops]
    # the instructor and the operator change things half way: the bank must route every change to one loop
    for k in range(200):
        if k == 60:
            for b, i in ((bank, 2), (alone[2], 0)):
                b.op_external[i] = 70.0
            for b, i in ((bank, 10), (alone[10], 0)):
                b.set_valve(i, S=1.0, J=0.2)
                b.set_sp(i, -0.5)
            for b, i in ((bank, 3), (alone[3], 0)):
                b.set_manual_op(i, 55.0)
            for b, i in ((bank, 20), (alone[20], 0)):
                b.set_load(i, 4.0)
                b.set_frozen(i, True)
        bank.step()
        for b in alone:
            b.step()
        for name in ("op", "mv", "flow", "pv", "sp", "stuck"):
            together = getattr(bank, name)
            apart = np.concatenate([getattr(b, name) for b in alone])
            assert np.array_equal(together, apart), f"{name} differs at step {k}"
    assert np.ptp(bank.pv) > 0 and bank.stuck.any() and not bank.stuck.all()   # the loops really moved


def test_fleet_bank_run_matches_each_loop_run_alone():
    cfg = mixed_fleet()
    out = LoopBank(cfg.loops, dt=cfg.device.tick).run(300)
    for i, lp in enumerate(cfg.loops):
        one = LoopBank([lp], dt=cfg.device.tick).run(300)
        for name in ("sp", "op", "mv", "flow", "pv", "stuck"):
            assert np.array_equal(out[name][:, i], one[name][:, 0]), (name, lp.name)


def test_loops_with_the_same_plant_share_one_discretisation(monkeypatch):
    import valve_emulator.simulation.loop as loop_module

    calls = []
    real = loop_module.transfer_functions_to_zoh
    monkeypatch.setattr(loop_module, "transfer_functions_to_zoh", lambda args: calls.append(args) or real(args))
    cfg = fleet(50, 10, vary={"S": [1.0, 5.0]})     # plants all equal, valves varied
    bank = LoopBank(cfg.loops, dt=0.1)
    assert len(calls) == 1 and len(calls[0]) == 1   # one batch holding the one distinct plant
    assert len({id(t) for t in bank.tables}) == 1 and len({id(c) for c in bank.characteristics}) == 1
    assert len(set(np.round(bank.S, 9))) == 50
