"""Closed loop: the 2003 paper's Table 1 statements, describing function vs simulation, determinism, banks."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.cli import main
from valve_emulator.config import DisturbanceConfig, load_loop
from valve_emulator.simulation.limit_cycle import measure_limit_cycle, predict_limit_cycle
from valve_emulator.simulation.loop import LoopBank, simulate_loop

TABLE1 = Path(__file__).resolve().parents[2] / "configs" / "table1"
CASES = ("no_stiction", "deadband", "undershoot", "no_offset", "overshoot")


def table1(loop, case):
    return load_loop(TABLE1 / f"{loop}_{case}.yaml")


def last_part(rec, fraction=0.4):
    sel = rec.t >= rec.t[-1] * (1 - fraction)
    return rec.op[sel], rec.mv[sel], rec.pv[sel]


def crest(x):
    """RMS over half peak-to-peak: 1/sqrt(3) = 0.577 for a triangle, 0.707 for a sine, 1 for a square."""
    x = x - x.mean()
    return np.sqrt(np.mean(x ** 2)) / (np.ptp(x) / 2)


def test_seed_form_values_are_converted():
    cfg = table1("concentration", "undershoot")
    assert (cfg.valve.S, cfg.valve.J) == (5.0, 2.0)  # seed s = 5, j = 1
    assert cfg.valve.seed_form == (5.0, 1.0)
    assert table1("level", "overshoot").valve.J == 4.5  # seed j = 2.25


@pytest.mark.parametrize("case", CASES)
def test_concentration_loop_cycles_exactly_when_the_seed_says(case):
    rec = simulate_loop(table1("concentration", case))
    lc = measure_limit_cycle(rec.t, rec.op)
    if case in ("no_stiction", "deadband"):
        # "In the absence of stiction there are no limit cycles ... pure deadband also can not produce any"
        assert not lc.sustained
        op, _, pv = last_part(rec, 0.1)
        assert np.ptp(op) < 0.5 and abs(pv.mean() - 1.0) < 0.1  # settled at the set point
    else:
        assert lc.sustained and lc.n_cycles >= 3
        assert lc.amplitude > 1.0
        op, _, _ = last_part(rec)
        assert crest(op) < 0.62, "OP should be triangular (seed Section 4.3)"


@pytest.mark.parametrize("case", CASES)
def test_level_loop_cycles_in_every_stiction_case_including_deadband(case):
    rec = simulate_loop(table1("level", case))
    lc = measure_limit_cycle(rec.t, rec.op)
    if case == "no_stiction":
        assert not lc.sustained
    else:
        # "with the presence of an integrator ... even a pure deadband can produce limit cycles"
        assert lc.sustained and lc.n_cycles >= 5 and lc.amplitude > 0.5


@pytest.mark.parametrize("case", CASES[1:])
def test_describing_function_predicts_level_loop_period_within_15_percent(case):
    cfg = table1("level", case)
    pred = predict_limit_cycle(cfg.valve.S, cfg.valve.J, cfg.controller, cfg.plant)
    rec = simulate_loop(cfg)
    meas = measure_limit_cycle(rec.t, rec.op)
    assert pred.found and meas.sustained
    assert abs(pred.period - meas.period) / meas.period < 0.15


def test_slip_jump_plain_in_mv_op_hidden_in_pv_op():
    rec = simulate_loop(table1("concentration", "undershoot"))
    _, mv, pv = last_part(rec)
    jump_mv = np.abs(np.diff(mv)).max() / (np.ptp(mv) / 2)
    jump_pv = np.abs(np.diff(pv)).max() / (np.ptp(pv) / 2)
    assert jump_mv > 0.5  # one sample carries most of the valve's half-range: the slip jump J
    assert jump_pv < 0.05  # the process dynamics smooth it away (seed Section 3 and Fig. 7)
    assert jump_mv > 20 * jump_pv


def test_same_config_and_seed_give_byte_identical_recordings(tmp_path):
    cfg = table1("concentration", "undershoot")
    noisy = replace(cfg, plant=replace(cfg.plant, noise=0.05,
                                       disturbance=DisturbanceConfig(type="random_walk", std=0.05)))
    from valve_emulator.recordings.recording import write_csv

    paths = []
    for k in range(2):
        paths.append(tmp_path / f"r{k}.csv")
        write_csv(simulate_loop(noisy, 300), paths[-1])
    assert paths[0].read_bytes() == paths[1].read_bytes()
    other = replace(noisy, simulation=replace(noisy.simulation, seed=1))
    write_csv(simulate_loop(other, 300), tmp_path / "other.csv")
    assert (tmp_path / "other.csv").read_bytes() != paths[0].read_bytes()


def test_bank_equals_loops_alone_and_step_equals_run():
    cfgs = [table1("concentration", "undershoot"), table1("level", "deadband"),
            replace(table1("level", "overshoot"), controller=None)]
    cfgs[1] = replace(cfgs[1], plant=replace(cfgs[1].plant, noise=0.01),
                      simulation=replace(cfgs[1].simulation, seed=4))
    steps = 2000
    together = LoopBank(cfgs).run(steps)
    for i, c in enumerate(cfgs):
        alone = LoopBank([c]).run(steps)
        for key in ("op", "mv", "pv", "sp"):
            np.testing.assert_array_equal(together[key][:, i], alone[key][:, 0])
    bank = LoopBank(cfgs)
    stepped = []
    for _ in range(steps):
        bank.step()
        stepped.append((bank.op.copy(), bank.mv, bank.pv.copy()))
    np.testing.assert_array_equal(np.array([s[0] for s in stepped]), together["op"])
    np.testing.assert_array_equal(np.array([s[1] for s in stepped]), together["mv"])
    np.testing.assert_array_equal(np.array([s[2] for s in stepped]), together["pv"])


def test_a_state_captured_before_pending_set_point_steps_restores_and_continues_sample_for_sample():
    """The schedule's pending steps are (t, value) tuples in memory (lists once read from a snapshot file):
    both are state a restore accepts, and the restored bank meets the later steps as the original does."""
    cfg = table1("concentration", "undershoot")
    cfg = replace(cfg, controller=replace(cfg.controller, sp_steps=((20.0, cfg.controller.sp + 2.0),
                                                                    (60.0, cfg.controller.sp - 1.0))))
    original, restored = LoopBank([cfg]), LoopBank([cfg])
    for _ in range(5):
        original.step()
    restored.set_state(original.state())
    for _ in range(int(100.0 / cfg.simulation.dt)):
        original.step()
        restored.step()
        np.testing.assert_array_equal(restored.pv, original.pv)
    assert original.sp[0] == cfg.controller.sp - 1.0


def test_external_op_is_held_and_drives_the_plant():
    cfg = replace(table1("concentration", "undershoot"), controller=None)
    bank = LoopBank([cfg], dt=0.1)
    mv0, pv0 = bank.mv[0], bank.pv[0]
    bank.op_external[0] = 51.0  # +1 % after rest in the +1 direction: less than J = 2, stuck
    bank.run(100)
    assert bank.mv[0] == mv0 and bank.pv[0] == pv0
    bank.op_external[0] = 52.5  # beyond J: breaks away, MV = OP - (S - J)/2
    bank.run(1000)
    assert bank.mv[0] == pytest.approx(52.5 - 1.5)
    assert bank.pv[0] == pytest.approx(3.0 * (bank.mv[0] - mv0), rel=1e-3)  # gain 3 after 100 s


def test_cli_simulate_writes_the_standard_recording_and_plot(tmp_path, capsys):
    out, png = tmp_path / "rec.csv", tmp_path / "fig.png"
    assert main(["simulate", str(TABLE1 / "level_undershoot.yaml"), "--duration", "60",
                 "--out", str(out), "--plot", str(png)]) == 0
    header = out.read_text().splitlines()[0].split(",")
    assert header[:5] == ["t", "sp", "op", "mv", "pv"]
    assert len(out.read_text().splitlines()) == 601 + 1
    assert png.stat().st_size > 10_000
    assert main(["simulate", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "x.csv")]) == 2
    assert not (tmp_path / "x.csv").exists()
    assert "missing.yaml" in capsys.readouterr().err


def test_cli_limit_cycle_prints_prediction_and_simulation(capsys):
    assert main(["limit-cycle", str(TABLE1 / "level_undershoot.yaml")]) == 0
    line = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("level_undershoot")][0]
    cells = line.split("|")
    df_period, sim_period = float(cells[1].split()[1]), float(cells[2].split()[1])
    assert abs(df_period - sim_period) / sim_period < 0.15


def test_instructor_faults_frozen_valve_load_and_noise():
    cfg = replace(table1("concentration", "no_stiction"), controller=None)
    bank = LoopBank([cfg])
    bank.set_frozen(0, True)
    bank.op_external[0] = 70.0
    bank.run(600)
    assert bank.mv[0] == 50.0 and bank.stuck[0]  # seized: OP moved 20 %, the valve did not
    bank.set_frozen(0, False)
    bank.run(10)
    assert bank.mv[0] == 70.0  # released, no stiction: follows OP
    bank.run(2000)
    pv_before = bank.pv[0]
    assert pv_before == pytest.approx(3.0 * 20.0, rel=1e-3)
    bank.set_load(0, -5.0)  # 5 % less flow reaches the process
    bank.run(2000)
    assert bank.pv[0] == pytest.approx(pv_before - 3.0 * 5.0, rel=1e-3)
    quiet = bank.run(100)["pv"][:, 0]
    assert np.ptp(quiet) < 1e-6  # still settling by ~1e-7: no noise yet
    bank.set_noise(0, 0.2)
    noisy = bank.run(2000)["pv"][:, 0]
    assert 0.17 < noisy.std() < 0.23
    with pytest.raises(ValueError, match="noise"):
        bank.set_noise(0, -1.0)
    assert bank.noise_std[0] == 0.2


def test_bank_shows_the_controller_tuning_as_read_only_copies():
    cfg = table1("concentration", "undershoot")
    bank = LoopBank([cfg, cfg])
    kc0, ti0 = cfg.controller.kc, cfg.controller.ti
    assert list(bank.kc) == [kc0, kc0] and list(bank.ti) == pytest.approx([ti0, ti0])
    bank.run(50)
    bank.set_tuning(1, kc=2 * kc0, ti=float("inf"), td=3.0)
    assert list(bank.kc) == [kc0, 2 * kc0] and bank.ti[1] == float("inf") and list(bank.td) == [0.0, 3.0]
    bank.kc[0] = 99.0                      # a copy: the bank's controller is untouched
    assert bank.kc[0] == kc0
