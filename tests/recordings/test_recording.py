"""The standard recording CSV: round trips, byte-identical output, and every rejected defect."""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from valve_emulator.recordings.recording import (
    CsvRecordingWriter,
    Recording,
    RecordingError,
    RecordingWarning,
    read_csv,
    write_csv,
)

HEADER = "t,sp,op,mv,pv\n"


def make_recording(n: int = 50, *, with_extra: bool = True) -> Recording:
    t = 0.1 * np.arange(n)
    rng = np.random.default_rng(1)
    mv = rng.uniform(0, 100, n)
    mv[3] = np.nan  # a missing valve position
    extra = {"flow": rng.normal(size=n), "noise": np.full(n, np.nan)} if with_extra else {}
    return Recording(t, np.full(n, 50.0), rng.uniform(0, 100, n), mv, 50 + rng.normal(size=n),
                     extra=extra, source="mem")


def write_text(tmp_path, text: str, name: str = "rec.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8", newline="")
    return p


def rows(n: int, dt: float = 0.5) -> str:
    return "".join(f"{k * dt!r},50.0,{40.0 + k!r},{39.0 + k!r},50.5\n" for k in range(n))


# ------------------------------------------------------------------------------------------- round trip

def test_round_trip_is_exact_and_keeps_extra_columns_in_order(tmp_path):
    rec = make_recording()
    p = tmp_path / "a.csv"
    write_csv(rec, p)
    back = read_csv(p)
    assert back.columns == ("t", "sp", "op", "mv", "pv", "flow", "noise")
    for name in rec.columns:
        np.testing.assert_array_equal(back.column(name), rec.column(name))  # NaN == NaN here, bits exact
    assert back.source == str(p)
    assert p.read_text().splitlines()[0] == "t,sp,op,mv,pv,flow,noise"
    assert p.read_text().splitlines()[4].split(",")[3] == ""  # NaN as an empty cell


def test_same_data_gives_byte_identical_files(tmp_path):
    p1, p2 = tmp_path / "1.csv", tmp_path / "2.csv"
    write_csv(make_recording(), p1)
    write_csv(read_csv(p1), p2)
    buf = io.StringIO()
    write_csv(make_recording(), buf)
    assert p1.read_bytes() == p2.read_bytes() == buf.getvalue().encode()


@settings(max_examples=60, deadline=None)
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=2, max_size=20))
def test_any_double_survives_the_round_trip(tmp_path_factory, values):
    n = len(values)
    v = np.array(values)
    rec = Recording(np.arange(n, dtype=float), v, np.zeros(n), v, np.ones(n), extra={"x": v})
    buf = io.StringIO()
    write_csv(rec, buf)
    p = tmp_path_factory.getbasetemp() / "hypothesis.csv"
    p.write_text(buf.getvalue(), encoding="utf-8", newline="")
    back = read_csv(p)
    for col in (back.sp, back.mv, back.extra["x"]):
        np.testing.assert_array_equal(col.view(np.int64)[~np.isnan(v)], v.view(np.int64)[~np.isnan(v)])
        assert np.array_equal(np.isnan(col), np.isnan(v))


def test_sp_and_mv_may_be_absent_or_empty(tmp_path):
    p = write_text(tmp_path, "t,op,pv,extra1\n0,1,2,\n1,1,2,3\n2,1,2,4\n")
    rec = read_csv(p)
    assert len(rec) == 3 and np.all(np.isnan(rec.sp)) and np.all(np.isnan(rec.mv))
    assert not rec.has_sp and not rec.has_mv
    np.testing.assert_array_equal(rec.extra["extra1"], [np.nan, 3, 4])
    p2 = write_text(tmp_path, "t,sp,op,mv,pv\r\n0,,1,,2\r\n1,5,1,,2\r\n", "crlf.csv")
    rec2 = read_csv(p2)
    assert rec2.has_sp and not rec2.has_mv and rec2.sp[1] == 5


def test_recording_object():
    rec = make_recording(10)
    assert len(rec) == 10 and rec.dt == pytest.approx(0.1)
    part = rec.slice(2, -3)
    assert len(part) == 5 and part.t[0] == rec.t[2] and part.extra["flow"][0] == rec.extra["flow"][2]
    assert np.shares_memory(part.op, rec.op)  # slices are views, not copies
    with pytest.raises(ValueError):
        rec.op[0] = 1.0  # read-only: a frozen recording cannot be changed behind its back
    src = np.arange(3.0)
    r = Recording(src, None, src, None, src)
    src[0] = 99.0
    assert r.t[0] == 0.0 and np.all(np.isnan(r.mv))
    with pytest.raises(ValueError, match="pv has 2 samples"):
        Recording(src, None, src, None, src[:2])
    with pytest.raises(ValueError, match="clashes"):
        Recording(src, None, src, None, src, extra={"op": src})
    with pytest.raises(ValueError, match="op is required"):
        Recording(src, None, None, None, src)
    with pytest.raises(ValueError, match="at least 2 samples"):
        _ = rec.slice(0, 1).dt


# ------------------------------------------------------------------------------------------- the writer

def test_incremental_writer_matches_write_csv_and_flushes_each_line(tmp_path):
    rec = make_recording(8)
    p = tmp_path / "inc.csv"
    with CsvRecordingWriter(p, extra_columns=("flow", "noise")) as w:
        for k in range(len(rec)):
            w.write_row(rec.t[k], rec.sp[k], rec.op[k], rec.mv[k], rec.pv[k],
                        rec.extra["flow"][k], rec.extra["noise"][k])
            # Another reader sees every completed row at once, without the writer closing.
            assert p.read_text().count("\n") == k + 2
        assert w.rows_written == 8
    assert w.closed
    ref = tmp_path / "ref.csv"
    write_csv(rec, ref)
    assert p.read_bytes() == ref.read_bytes()


def test_writer_rejects_bad_rows_without_writing(tmp_path):
    p = tmp_path / "w.csv"
    w = CsvRecordingWriter(p, fsync=True)
    with pytest.raises(ValueError, match="closed"):
        w.write_row(0, 1, 2, 3, 4)
    with w:
        w.write_row(0.0, 1, 2, 3, 4)
        before = p.read_bytes()
        for bad in [(0.0, 1, 2, 3, 4), (-1.0, 1, 2, 3, 4), (math.nan, 1, 2, 3, 4), (1.0, 1, math.inf, 3, 4),
                    (1.0, 1, 2, 3, math.nan), (1.0, 1, 2, 3, 4, 5)]:
            with pytest.raises(ValueError):
                w.write_row(*bad)
        assert p.read_bytes() == before
    with pytest.raises(ValueError, match="duplicate"):
        CsvRecordingWriter(p, extra_columns=("a", "a"))
    with pytest.raises(ValueError, match="clashes"):
        CsvRecordingWriter(p, extra_columns=("pv",))


def test_killed_writer_leaves_a_readable_file(tmp_path):
    p = tmp_path / "killed.csv"
    with CsvRecordingWriter(p) as w:
        for k in range(5):
            w.write_row(k * 1.0, 50.0, 40.0 + k, 39.0 + k, 50.0)
    full = p.read_bytes()
    p.write_bytes(full + b"5.0,50.0,4")  # the process died after writing part of row 6
    with pytest.warns(RecordingWarning, match=r"line 7: dropped an incomplete last line"):
        rec = read_csv(p)
    assert len(rec) == 5
    p.write_bytes(full + b"5.0,50.0,45.0,44.0,50.0")  # a last row complete but for its newline is kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = read_csv(p)
    assert len(rec) == 6 and rec.pv[-1] == 50.0
    p.write_bytes(full + b"1")  # parses as a number but t goes back: still a cut-short line
    with pytest.warns(RecordingWarning):
        assert len(read_csv(p)) == 5


# ------------------------------------------------------------------------------------------- the checks

@pytest.mark.parametrize(("text", "message"), [
    ("", r"line 1: the file is empty"),
    ("\n\n", r"line 1: the file is empty"),
    ("t,sp,op,mv\n0,1,2,3\n1,1,2,3\n", r"line 1, column 'pv': missing required column"),
    ("t,op,op,pv\n", r"line 1, column 'op' \(3\): duplicate of column 2"),
    ("t,,op,pv\n", r"line 1, column 2: empty column name"),
    (HEADER + rows(2) + "1.0,50,41,40\n" + rows(1),
     r"line 4: expected 5 cells, found 4 \(column 'pv' \(5\) is missing\)"),
    (HEADER + rows(2) + "1.0,50,41,40,1,2\n", r"line 4: expected 5 cells, found 6 \(cell 6 is beyond"),
    (HEADER + rows(2) + "\n" + "1.0,50,41,40,50\n", r"line 4: blank line inside the data"),
    (HEADER + rows(3) + "1.5,50,abc,40,50\n", r"line 5, column 'op' \(3\): not a number: 'abc'"),
    (HEADER + "0,50,1,1,x\n", r"line 2, column 'pv' \(5\): not a number"),
    (HEADER + rows(2) + "1.0,50,,40,50\n", r"line 4, column 'op' \(3\): empty cell; op is required"),
    (HEADER + rows(2) + "inf,50,41,40,50\n", r"line 4, column 't' \(1\): t must be finite"),
    (HEADER + rows(2) + "nan,50,41,40,50\n", r"line 4, column 't' \(1\): t must be finite"),
    (HEADER + rows(2) + "1.0,50,inf,40,50\n", r"line 4, column 'op' \(3\): op must be finite"),
    (HEADER + rows(3) + "0.5,50,41,40,50\n",
     r"line 5, column 't' \(1\): t must increase strictly; t = 0.5 goes back from t = 1.0 on line 4"),
    (HEADER + rows(3) + "1.0,50,41,40,50\n",
     r"line 5, column 't' \(1\): t must increase strictly; t = 1.0 repeats"),
    (HEADER + rows(5) + "3.0,50,41,40,50\n",
     r"line 7, column 't' \(1\): gap in t: step of 1.0 s from line 6 is more than 1.5 x the median"),
    (HEADER + rows(1), r"line 2: 1 data row\(s\), at least min_samples=2 needed"),
    ("t,op,pv", r"line 1: 0 data row\(s\)"),
])
def test_defects_are_reported_with_file_line_and_column(tmp_path, text, message):
    p = write_text(tmp_path, text)
    with pytest.raises(RecordingError, match=rf"^{p}: {message}"):
        read_csv(p)


def test_utf8_error_names_byte_offset(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_bytes(HEADER.encode() + b"0,1,2,3,4\n1,1,2,\xff,4\n")
    with pytest.raises(RecordingError, match=rf"^{p}: line 3: not UTF-8 text at byte offset 30"):
        read_csv(p)


def test_options_and_tolerated_forms(tmp_path):
    irregular = HEADER + rows(5) + "3.0,50,41,40,50\n"
    p = write_text(tmp_path, irregular)
    assert len(read_csv(p, gap_factor=None)) == 6
    assert len(read_csv(p, gap_factor=3.0)) == 6
    one = write_text(tmp_path, HEADER + rows(1), "one.csv")
    assert len(read_csv(one, min_samples=1)) == 1
    # A byte-order mark, spaces around names and cells, and an editor's extra newline at the end.
    p2 = write_text(tmp_path, "\ufefft , op,pv\n0, 1 ,2\n1,1,2\n\n", "bom.csv")
    assert len(read_csv(p2)) == 2
    with pytest.raises(ValueError, match="gap_factor"):
        read_csv(p, gap_factor=0.5)
    with pytest.raises(ValueError, match="min_samples"):
        read_csv(p, min_samples=-1)
