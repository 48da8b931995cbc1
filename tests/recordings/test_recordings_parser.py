"""The one text parser under every recording reader: properties (hypothesis) and what it now guarantees.

* the standard CSV round-trips any finite doubles bit for bit, in every column, ``t`` included;
* a standard recording is detected as such, and only when no column mapping is asked for;
* a ``;``-separated file with a decimal comma reads to the very numbers of the same file with ``,`` and ``.``;
* the DECIMAL number syntax reads a whole column at once exactly as cell by cell: a cell is accepted only when
  it is a plain decimal number, and then has the value ``float`` gives it;
* errors carry the file, line and column as attributes.
"""

from __future__ import annotations

import pickle
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from valve_emulator.recordings import (
    Format,
    ReaderError,
    Recording,
    RecordingError,
    detect_format,
    read_recording,
)
from valve_emulator.recordings.recording import read_csv, write_csv
from valve_emulator.recordings.table import NumberSyntax, Table
from valve_emulator.recordings.text import split_lines

FINITE = st.floats(allow_nan=False, allow_infinity=False)
_PLAIN = re.compile(r"\s*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\s*")


def _bits(a: np.ndarray) -> list[int]:
    return np.asarray(a, dtype=np.float64).view(np.int64).tolist()


@st.composite
def finite_recordings(draw) -> Recording:
    """Any finite doubles (subnormals, -0.0, 1e308 ...) in every column; ``t`` strictly increasing."""
    t = sorted(draw(st.lists(FINITE, min_size=2, max_size=25, unique=True)))
    n = len(t)
    col = st.lists(FINITE, min_size=n, max_size=n)
    names = draw(st.lists(st.sampled_from(["flow", "T_in", "x1"]), max_size=2, unique=True))
    return Recording(t, draw(col), draw(col), draw(col), draw(col), extra={k: draw(col) for k in names})


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rec=finite_recordings())
def test_write_then_read_returns_every_finite_double_exactly(tmp_path, rec):
    path = tmp_path / "r.csv"
    write_csv(rec, path)
    back = read_csv(path, gap_factor=None)
    assert back.columns == rec.columns
    for name in rec.columns:
        assert _bits(back.column(name)) == _bits(rec.column(name)), name


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rec=finite_recordings())
def test_a_standard_file_is_detected_as_standard(tmp_path, rec):
    path = tmp_path / "s.csv"
    write_csv(rec, path)
    lines = split_lines(path.read_text(encoding="utf-8"), str(path))
    assert detect_format(lines) is Format.STANDARD
    # Asking for a column mapping, or skipping lines, means the caller says it is not the standard format.
    assert detect_format(lines, mapped=True) is Format.CSV
    assert detect_format(lines, skip=1) is Format.CSV
    loaded = read_recording(path, gap_factor=None, min_samples=1)
    assert loaded.source_format == "standard"
    assert _bits(loaded.full.pv) == _bits(rec.pv) and _bits(loaded.full.mv) == _bits(rec.mv)


@pytest.mark.parametrize(("header", "options", "expected"), [
    ("t,sp,op,mv,pv", {}, Format.STANDARD),
    ("op,pv,t", {}, Format.STANDARD),                        # names t, op and pv in any order
    ("t,sp,mv,pv", {}, Format.STANDARD),                     # starts with t: a standard file missing op
    ("t,OUT,FLOW", {}, Format.STANDARD),
    ("t,OUT,FLOW", {"mapped": True}, Format.CSV),            # a mapping is asked for: generic delimited text
    ("t,OUT,FLOW", {"op_units": "mA"}, Format.CSV),          # OP in mA is not the standard format either
    ("t,OUT,FLOW", {"encoding": "gb18030"}, Format.CSV),
    ("t,op,pv", {"op_units": "mA"}, Format.STANDARD),        # ... but a header naming t, op, pv still is
    ("t", {}, Format.CSV),                                   # one cell is not a table
    ("time,op,pv", {}, Format.CSV),
    ("t;op;pv", {}, Format.CSV),
    ("PROCESSDATA\tFIC101 Data", {}, Format.DCS),
])
def test_detection_rule(header, options, expected):
    assert detect_format([header, "0,1,2"], **options) is expected


def test_auto_gives_the_standard_readers_error_for_a_standard_file_missing_a_column(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("t,sp,mv,pv\n" + "".join(f"{k}.0,,,1.0\n" for k in range(5)), encoding="utf-8")
    with pytest.raises(ReaderError, match=r"m\.csv: line 1, column 'op': missing required column") as exc:
        read_recording(path)
    assert (exc.value.line, exc.value.column) == (1, "op")


@st.composite
def decimal_tables(draw) -> tuple[list[float], list[float]]:
    n = draw(st.integers(2, 30))
    col = st.lists(st.one_of(FINITE, st.integers(-10**6, 10**6).map(float)), min_size=n, max_size=n)
    return draw(col), draw(col)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=decimal_tables())
def test_decimal_comma_and_semicolon_read_the_same_numbers_as_point_and_comma(tmp_path, data):
    op, pv = data
    point = "".join(f"{k},{a!r},{b!r}\n" for k, (a, b) in enumerate(zip(op, pv)))
    comma = "".join(f"{k};{a!r};{b!r}\n".replace(".", ",") for k, (a, b) in enumerate(zip(op, pv)))
    (tmp_path / "point.csv").write_text("time,op,pv\n" + point, encoding="utf-8")
    (tmp_path / "comma.csv").write_text("time;op;pv\n" + comma, encoding="utf-8")
    (tmp_path / "std.csv").write_text("t,op,pv\n" + point, encoding="utf-8")
    a = read_recording(tmp_path / "point.csv").recording
    b = read_recording(tmp_path / "comma.csv", decimal=",").recording
    c = read_recording(tmp_path / "std.csv").recording          # the standard reader, same parser
    assert (a.op.tolist(), a.pv.tolist()) == (op, pv)
    for rec in (b, c):
        assert _bits(rec.op) == _bits(a.op) and _bits(rec.pv) == _bits(a.pv) and _bits(rec.t) == _bits(a.t)


@settings(max_examples=300, deadline=None)
@given(cells=st.lists(st.one_of(st.text(alphabet="0123456789eE+-. ", max_size=8),
                                st.from_regex(_PLAIN, fullmatch=True)), min_size=1, max_size=6),
       decimal=st.sampled_from([".", ","]))
@pytest.mark.slow
def test_decimal_syntax_reads_a_column_as_each_cell_alone(cells, decimal):
    """The whole-column fast path accepts exactly the plain decimal numbers, with ``float``'s value."""
    text = [c.replace(".", decimal) for c in cells]
    table = Table("f.csv", ["x"], [[c] for c in text], first_line=2)
    expected = []
    for c in (c.strip() for c in cells):                    # a cell is read without its surrounding spaces
        if not c or _PLAIN.fullmatch(c) is None or not np.isfinite(float(c)):
            expected = None
            break
        expected.append(float(c))
    if expected is None:
        with pytest.raises(ReaderError, match=r"^f\.csv: line \d+, column 'x' \(1\): (not a number|empty cell|"
                                              r"number out of range)"):
            table.numbers(0, decimal=decimal)
    else:
        assert _bits(table.numbers(0, decimal=decimal)) == _bits(np.array(expected))


def test_python_syntax_reads_inf_and_nan_and_decimal_syntax_refuses_them():
    table = Table("f.csv", ["x"], [["inf"], [" -inf "], ["nan"], ["1e999"], [""]], first_line=2)
    got = table.numbers(0, syntax=NumberSyntax.PYTHON, required=False)
    assert got[:4].tolist()[:2] == [np.inf, -np.inf] and np.isnan(got[2]) and got[3] == np.inf and np.isnan(got[4])
    with pytest.raises(ReaderError, match=r"line 2, column 'x' \(1\): not a number: 'inf'"):
        table.numbers(0, required=False)
    with pytest.raises(ReaderError, match=r"line 5, column 'x' \(1\): number out of range: '1e999'"):
        Table("f.csv", ["x"], [["1"], ["2"], ["3"], ["1e999"]], first_line=2).numbers(0)


def test_errors_carry_file_line_and_column_and_survive_pickling(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("t,sp,op,mv,pv\n0,1,2,3,4\n1,1,abc,3,4\n", encoding="utf-8")
    with pytest.raises(RecordingError) as exc:
        read_csv(path)
    err = exc.value
    assert isinstance(err, ReaderError) and isinstance(err, ValueError)
    assert (err.source, err.line, err.column) == (str(path), 3, "op")
    back = pickle.loads(pickle.dumps(err))
    assert str(back) == str(err) and (back.source, back.line, back.column) == (err.source, err.line, err.column)
    path.write_text("time;op;pv\n0;1;2\n1;1;2\n1;1;2\n", encoding="utf-8")    # the delimited reader, too
    with pytest.raises(ReaderError, match=r"line 4, column 'time' \(1\): time stamp '1' repeats line 3") as exc:
        read_recording(path)
    assert (exc.value.source, exc.value.line, exc.value.column) == (str(path), 4, "time")


def test_quoted_cells_and_lone_cr_line_ends_are_read_by_every_reader(tmp_path):
    path = tmp_path / "q.csv"
    path.write_bytes(b't,op,pv\r"0",1,"2"\r1,1,3\r')
    rec = read_csv(path)
    assert rec.t.tolist() == [0.0, 1.0] and rec.pv.tolist() == [2.0, 3.0]
    assert read_recording(path).source_format == "standard"
    # A quote left open stays on its own line: the next line is still a row, with its own number in messages
    # (a CSV parser fed all lines at once would have swallowed it into the open cell).
    path.write_text('time,op,pv,note\n0,1,2,"open\n1,x,2,z\n', encoding="utf-8")
    with pytest.raises(ReaderError, match=r"q\.csv: line 3, column 'op' \(2\): not a number: 'x'"):
        read_recording(path)
