"""Signal chain: mA <-> % look-up table, saturation, flow characteristics, the whole valve."""

import numpy as np
import pytest

from valve_emulator.cli import main
from valve_emulator.physics.signal_chain import Characteristic, LookupTable, ValveChain, saturate
from valve_emulator.stiction import simulate


def test_default_table_is_4_20_ma_with_linear_extension():
    t = LookupTable()
    np.testing.assert_allclose(t.to_pct([4, 12, 20, 3.8, 20.8]), [0, 50, 100, -1.25, 105])
    np.testing.assert_allclose(t.to_ma([0, 50, 100]), [4, 12, 20])
    # The 2003 paper: with 4-20 mA, 2 % stiction is 0.32 mA
    assert t.to_ma(2.0) - t.to_ma(0.0) == pytest.approx(0.32)


def test_any_monotone_table_round_trips_including_a_falling_one():
    rising = LookupTable(((4, 0), (8, 10), (20, 100)))
    falling = LookupTable(((4, 100), (20, 0)))  # air-to-close
    x = np.linspace(0, 100, 41)
    for table in (rising, falling):
        np.testing.assert_allclose(table.to_pct(table.to_ma(x)), x, atol=1e-12)
    assert rising.to_pct(6) == pytest.approx(5.0)
    assert falling.to_pct(4) == 100 and falling.to_pct(20) == 0


@pytest.mark.parametrize("points, word", [
    (((4, 0),), "at least two"),
    (((4, 0), (4, 100)), "strictly increasing"),
    (((4, 0), (8, 50), (20, 40)), "monotone"),
    (((4, 0), (20, float("nan"))), "finite"),
])
def test_bad_tables_are_refused(points, word):
    with pytest.raises(ValueError, match=word):
        LookupTable(points)


def test_characteristics_match_their_definitions():
    x = np.array([0.0, 25.0, 50.0, 100.0])
    np.testing.assert_allclose(Characteristic("linear").flow(x), x)
    eq = Characteristic("equal_percentage", 50.0)
    np.testing.assert_allclose(eq.flow(x), 100 * 50.0 ** (x / 100 - 1))
    assert eq.flow(0.0) == pytest.approx(2.0)  # f(0) = 1/R, not 0
    np.testing.assert_allclose(Characteristic("quick_opening").flow(x), 100 * np.sqrt(x / 100))
    for c in (Characteristic("linear"), eq, Characteristic("quick_opening")):
        y = np.linspace(5, 95, 19)
        np.testing.assert_allclose(c.travel(c.flow(y)), y, atol=1e-9)
        h = 1e-6
        np.testing.assert_allclose(c.gain(y), (c.flow(y + h) - c.flow(y - h)) / (2 * h) / 1.0, rtol=1e-5)
    with pytest.raises(ValueError, match="characteristic"):
        Characteristic("square_root")
    with pytest.raises(ValueError, match="rangeability"):
        Characteristic("equal_percentage", 1.0)


def test_chain_in_ma_equals_stiction_on_saturated_percent():
    rng = np.random.default_rng(0)
    ma = 12 + np.cumsum(rng.normal(0, 0.2, 2000))  # wanders beyond 4..20 too
    chain = ValveChain(1, S=4.0, J=1.0, characteristic=Characteristic("equal_percentage", 30.0))
    pct = LookupTable().to_pct(ma)
    chain.reset(saturate(pct[0]))
    mv = np.array([chain.step_ma(np.array([m]))[0] for m in ma])
    np.testing.assert_array_equal(mv, simulate(saturate(pct), S=4.0, J=1.0))
    assert mv.min() >= 0 and mv.max() <= 100
    np.testing.assert_allclose(chain.position_ma(mv), 4 + 0.16 * mv)
    np.testing.assert_allclose(chain.flow(mv[-1:]), Characteristic("equal_percentage", 30.0).flow(mv[-1:]))


def test_figure5_command_writes_png_and_csv(tmp_path):
    assert main(["figure5", "--out", str(tmp_path)]) == 0
    png, csv = tmp_path / "figure5.png", tmp_path / "figure5.csv"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    data = np.genfromtxt(csv, delimiter=",", names=True)
    assert data.dtype.names == ("t", "op", "mv_no_stiction", "mv_deadband", "mv_undershoot", "mv_no_offset",
                                "mv_overshoot")
    np.testing.assert_array_equal(data["mv_no_stiction"], data["op"])
    late = data["t"][1:] > 50
    for name, sign in (("mv_undershoot", -1), ("mv_overshoot", 1)):
        mv, op = data[name], data["op"]
        moving_up = late & (np.diff(op) > 0) & (np.diff(mv) > 0)  # samples where the valve moved upward
        err = (mv[1:] - op[1:])[moving_up]
        assert err.size > 100 and np.all(sign * err > 0)  # undershoot lags OP, overshoot passes it
