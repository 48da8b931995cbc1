"""Readers for real recordings (valve_emulator.recordings): formats, column mapping, units, MANUAL segments, errors.

Every file is written here into tmp_path; nothing reads the shared plant data.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from valve_emulator.recordings import ReaderError, read_recording
from valve_emulator.recordings.recording import Recording, RecordingError, write_csv

TAG = "2111FIC46005"


def grid_stamps(n, ts=10):
    t0 = datetime(2024, 6, 13, 21, 55, 0)
    return [(t0 + timedelta(seconds=k * ts)).strftime("%Y-%m-%d %H:%M:%S") for k in range(n)]


def write_dcs(path, op, pv, sp, *, mode=None, stamps=None, ts=10, flags=None, declared_rows=None):
    """A file in the refinery DCS export layout (tab-separated, CRLF, UTF-8 Chinese descriptions)."""
    n = len(op)
    mode = [1] * n if mode is None else mode
    flags = [0] * n if flags is None else flags
    if stamps is None:
        stamps = grid_stamps(n, ts)
    cols = [f"{TAG}.MV", f"{TAG}.PV", f"{TAG}.SV", f"{TAG}.MODE", "bOpOFL", "bPvOFL", "bSpOFL", "bAutOFL"]
    lines = [
        f"PROCESSDATA\t{TAG} Data\tyyyy-MM-dd HH:mm:ss",
        f"8\t{ts}\t{stamps[0]}\t{n if declared_rows is None else declared_rows}",
        "tagname\t" + "\t".join(cols),
        "desc\t常减压装置_OP\t常减压装置_PV\t常减压装置_SP\tAut\tbOpOFL\tbPvOFL\tbSpOFL\tbAutOFL",
        "fsMax=1.63\tfsMin=0\tfsGridNum=10\tfdMax=1.63tfdMin=0\tfdGridNum=10\tv0GridNum=10\tL=24",
    ]
    for k in range(n):
        lines.append("\t".join([stamps[k], repr(float(op[k])), repr(float(pv[k])), repr(float(sp[k])), str(mode[k]),
                                str(flags[k]), str(flags[k]), str(flags[k]), str(flags[k])]))
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("utf-8"))
    return path


@pytest.fixture
def loop_data():
    k = np.arange(40)
    op = 50.0 + 5.0 * np.sin(k / 3.0)
    pv = 970.0 + 2.0 * np.cos(k / 3.0)
    sp = np.full(40, 970.0)
    return op, pv, sp


# ------------------------------------------------------------------------------------------------ DCS export

def test_dcs_export_is_detected_and_mv_is_read_as_op(tmp_path, loop_data):
    op, pv, sp = loop_data
    path = write_dcs(tmp_path / "stic_2111FIC46005.txt", op, pv, sp, flags=[1] + [0] * 39)
    loaded = read_recording(path)
    rec = loaded.recording
    assert loaded.source_format == "dcs"
    assert loaded.tag == TAG
    assert loaded.description == "常减压装置_PV"
    assert loaded.start == "2024-06-13 21:55:00"
    assert loaded.columns["op"] == f"{TAG}.MV" and loaded.columns["sp"] == f"{TAG}.SV"
    np.testing.assert_array_equal(rec.op, op)       # .MV is the controller output
    np.testing.assert_array_equal(rec.pv, pv)
    np.testing.assert_array_equal(rec.sp, sp)
    np.testing.assert_array_equal(rec.t, 10.0 * np.arange(40))
    assert not rec.has_mv                             # the DCS does not record the valve position
    assert loaded.excluded == () and loaded.info["declared_ts"] == "10"
    assert "bPvOFL" in rec.extra and any("bPvOFL is set on 1 of 40" in n for n in loaded.notes)


def test_dcs_manual_samples_are_excluded_and_reported(tmp_path, loop_data):
    op, pv, sp = loop_data
    mode = [1] * 10 + [0] * 5 + [1] * 25            # MANUAL from t = 100 s to t = 140 s
    loaded = read_recording(write_dcs(tmp_path / "m.txt", op, pv, sp, mode=mode))
    assert loaded.excluded == ((100.0, 140.0),)
    assert loaded.auto_segments == ((0.0, 90.0), (150.0, 390.0))
    rec = loaded.recording                           # the longest AUTO segment, in file time
    assert len(rec) == 25 and rec.t[0] == 150.0
    np.testing.assert_array_equal(rec.op, op[15:])
    assert [len(s) for s in loaded.segments()] == [10, 25]
    assert len(loaded.full) == 40
    assert "excluded (not AUTO): 100..140 s" in loaded.report()
    # mode=False ignores the mode column
    assert len(read_recording(tmp_path / "m.txt", mode=False).recording) == 40


def test_dcs_all_manual_is_an_error(tmp_path, loop_data):
    op, pv, sp = loop_data
    path = write_dcs(tmp_path / "man.txt", op, pv, sp, mode=[0] * 40)
    with pytest.raises(ReaderError, match=r"man\.txt: no sample is in AUTO mode"):
        read_recording(path)


def test_dcs_stamps_off_the_grid_use_the_declared_sample_time(tmp_path, loop_data):
    op, pv, sp = loop_data
    stamps = grid_stamps(40)
    stamps[5] = stamps[4]                            # a repeated stamp followed by a skipped one
    loaded = read_recording(write_dcs(tmp_path / "j.txt", op, pv, sp, stamps=stamps))
    np.testing.assert_array_equal(loaded.recording.t, 10.0 * np.arange(40))
    assert any("off the declared 10 s grid" in n for n in loaded.notes)


def test_dcs_time_going_backwards_names_both_lines(tmp_path, loop_data):
    op, pv, sp = loop_data
    stamps = grid_stamps(40)
    stamps[7], stamps[8] = stamps[8], stamps[7]
    with pytest.raises(ReaderError, match=r"b\.txt: line 14, column 'timestamp' \(1\): time goes backwards.*"
                                          r"on line 13"):
        read_recording(write_dcs(tmp_path / "b.txt", op, pv, sp, stamps=stamps))


def test_dcs_columns_can_be_overridden_by_suffix_or_number(tmp_path, loop_data):
    op, pv, sp = loop_data
    path = write_dcs(tmp_path / "o.txt", op, pv, sp)
    loaded = read_recording(path, op="PV", pv=2)     # deliberately swapped: suffix and 1-based number
    np.testing.assert_array_equal(loaded.recording.op, pv)
    np.testing.assert_array_equal(loaded.recording.pv, op)


def test_dcs_header_mismatch_is_noted(tmp_path, loop_data):
    op, pv, sp = loop_data
    loaded = read_recording(write_dcs(tmp_path / "n.txt", op, pv, sp, declared_rows=751))
    assert any("declares 751 rows, the file has 40" in n for n in loaded.notes)


# ------------------------------------------------------------------------------------- standard and generic

def test_standard_recording_round_trip(tmp_path):
    t = 0.5 * np.arange(20)
    rec = Recording(t + 3.0, np.full(20, 1.0), np.linspace(40, 60, 20), np.linspace(39, 59, 20),
                    np.sin(t), extra={"flow": np.ones(20)})
    write_csv(rec, tmp_path / "std.csv")
    loaded = read_recording(tmp_path / "std.csv")
    assert loaded.source_format == "standard"
    np.testing.assert_array_equal(loaded.recording.t, t)          # from the first sample
    np.testing.assert_array_equal(loaded.recording.mv, rec.mv)    # the standard format keeps MV
    np.testing.assert_array_equal(loaded.recording.extra["flow"], np.ones(20))
    with pytest.raises(ReaderError, match="fixed columns"):
        read_recording(tmp_path / "std.csv", fmt="standard", ts=1.0)


def test_generic_csv_with_title_lines_decimal_comma_and_names(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("Plant export\nunits: %; m3/h\nTime;OUT;FLOW;SP\n"
                    "0;1,5;10,25;10\n1;1,6;10,5;10\n2;1,7;-1,75e1;10\n", encoding="utf-8")
    loaded = read_recording(path, skip=2, decimal=",", op="OUT", pv="flow", pv_units="m3/h")
    rec = loaded.recording
    assert loaded.source_format == "csv" and loaded.info["delimiter"] == ";"
    np.testing.assert_array_equal(rec.op, [1.5, 1.6, 1.7])
    np.testing.assert_array_equal(rec.pv, [10.25, 10.5, -17.5])
    np.testing.assert_array_equal(rec.sp, [10.0, 10.0, 10.0])        # 'SP' found by name
    np.testing.assert_array_equal(rec.t, [0.0, 1.0, 2.0])
    assert loaded.pv_units == "m3/h" and loaded.columns["time"] == "Time"


def test_seconds_with_a_decimal_comma_are_a_time_column(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("Zeit;OUT;FLOW\n0,0;1,5;10\n0,5;1,6;11\n1,0;1,7;12\n", encoding="utf-8")
    rec = read_recording(path, decimal=",", time="Zeit", op="OUT", pv="FLOW").recording
    np.testing.assert_array_equal(rec.t, [0.0, 0.5, 1.0])
    np.testing.assert_array_equal(rec.op, [1.5, 1.6, 1.7])


def test_generic_tsv_without_header_uses_ts_and_column_numbers(tmp_path):
    path = tmp_path / "log.tsv"
    path.write_text("a\t40.0\t1.0\nb\t41.0\t1.5\nc\t42.0\t2.0\n", encoding="utf-8")
    rec = read_recording(path, header=False, op=2, pv="3", ts=2.5).recording
    np.testing.assert_array_equal(rec.t, [0.0, 2.5, 5.0])
    np.testing.assert_array_equal(rec.op, [40.0, 41.0, 42.0])
    assert not rec.has_sp


def test_datetime_time_column_is_converted_to_seconds(tmp_path):
    path = tmp_path / "dt.csv"
    path.write_text("timestamp,op,pv\n2025-01-01T23:59:58,1,2\n2025-01-02T00:00:00.5,1,2\n"
                    "2025-01-02 00:00:03,1,2\n", encoding="utf-8")
    loaded = read_recording(path, gap_factor=None)
    np.testing.assert_allclose(loaded.recording.t, [0.0, 2.5, 5.0])
    assert loaded.start == "2025-01-01T23:59:58"


def test_op_in_ma_is_converted_to_percent(tmp_path):
    path = tmp_path / "ma.csv"
    path.write_text("t,OP_mA,PV\n0,4,1\n1,12,2\n2,20,3\n3,3.2,4\n", encoding="utf-8")
    loaded = read_recording(path, op="OP_mA", pv="PV", op_units="mA")
    np.testing.assert_allclose(loaded.recording.op, [0.0, 50.0, 100.0, -5.0])   # 4-20 mA, extended linearly
    assert loaded.op_units == "mA"
    reverse = read_recording(path, op="OP_mA", pv="PV", op_units="mA", ma_table=[[4, 100], [20, 0]])
    np.testing.assert_allclose(reverse.recording.op, [100.0, 50.0, 0.0, 105.0])
    with pytest.raises(ReaderError, match="ma_table"):
        read_recording(path, op="OP_mA", pv="PV", op_units="mA", ma_table=[[4, 0]])


def test_pv_scale_is_the_robust_range_in_pv_units(tmp_path):
    pv = np.linspace(0.0, 1000.0, 1001)
    pv[500] = 1e6                                    # one spike does not set the scale
    path = tmp_path / "s.csv"
    path.write_text("t,op,pv\n" + "".join(f"{k},50,{float(v)!r}\n" for k, v in enumerate(pv)), encoding="utf-8")
    loaded = read_recording(path)
    assert loaded.pv_scale == pytest.approx(990.0, rel=2e-3)


def test_mode_column_with_text_values(tmp_path):
    path = tmp_path / "mode.csv"
    rows = "".join(f"{k},50,1,{'AUTO' if k < 3 or k > 5 else 'MAN'}\n" for k in range(12))
    path.write_text("t,op,pv,mode\n" + rows, encoding="utf-8")
    loaded = read_recording(path)
    assert loaded.excluded == ((3.0, 5.0),)
    assert len(loaded.recording) == 6 and loaded.recording.t[0] == 6.0


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(min_value=-1e6, max_value=1e6, allow_nan=False), min_size=2, max_size=30))
def test_decimal_comma_values_read_back_exactly(tmp_path_factory, values):
    path = tmp_path_factory.mktemp("h") / "v.csv"
    body = "".join(f"{k};{repr(v).replace('.', ',')};1\n" for k, v in enumerate(values))
    path.write_text("t;op;pv\n" + body, encoding="utf-8")
    rec = read_recording(path, decimal=",").recording
    assert rec.op.tolist() == values


# ----------------------------------------------------------------------------------------------- bad input

def test_unknown_format_names_the_file_and_the_expected_formats(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello world\nthis is not a recording\n", encoding="utf-8")
    with pytest.raises(ReaderError) as exc:
        read_recording(path)
    msg = str(exc.value)
    assert "notes.txt" in msg and "cannot detect the format" in msg and "PROCESSDATA" in msg
    assert isinstance(exc.value, (RecordingError, ValueError))


def test_missing_column_lists_the_available_ones(tmp_path, loop_data):
    op, pv, sp = loop_data
    path = write_dcs(tmp_path / "c.txt", op, pv, sp)
    with pytest.raises(ReaderError, match=r"c\.txt: op='VALVE': no such column; the columns are 1: "
                                          r"'timestamp', 2: '2111FIC46005.MV'"):
        read_recording(path, op="VALVE")
    csv_path = tmp_path / "x.csv"
    csv_path.write_text("time,OUT,FLOW\n0,1,2\n1,1,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"x\.csv: line 1: no column called 'op'; pass op=.*1: 'time', "
                                          r"2: 'OUT', 3: 'FLOW'"):
        read_recording(csv_path)
    with pytest.raises(ReaderError, match=r"op=9: column numbers are 1-based and the file has 3 columns"):
        read_recording(csv_path, op=9, pv="FLOW")


def test_mixed_encodings_name_the_byte_offset(tmp_path):
    path = tmp_path / "mixed.txt"
    good = "t,op,pv\n0,1,2\n# 注释\n".encode()
    path.write_bytes(good + "1,2,3 °C\n".encode("latin-1"))
    with pytest.raises(ReaderError) as exc:
        read_recording(path)
    msg = str(exc.value)
    assert "mixed.txt: line 4" in msg and f"byte offset {len(good) + 6}" in msg
    assert "UTF-8" in msg and "mixes encodings" in msg


def test_other_single_encoding_is_refused_with_a_hint_and_read_when_named(tmp_path):
    path = tmp_path / "gbk.csv"
    path.write_bytes("时间,op,pv\n0,1,2\n1,1,3\n".encode("gbk"))
    with pytest.raises(ReaderError, match=r"gbk\.csv: line 1: not UTF-8 text at byte offset 2.*encoding="):
        read_recording(path)
    rec = read_recording(path, encoding="gb18030", time="时间").recording
    np.testing.assert_array_equal(rec.pv, [2.0, 3.0])


def test_non_numeric_cell_names_line_and_column(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("t,op,pv\n0,1,2\n1,Bad,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"bad\.csv: line 3, column 'op' \(2\): not a number: 'Bad'"):
        read_recording(path, fmt="csv")
    path.write_text("t;op;pv\n0;1,5;2\n1;1,6;2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"line 2, column 'op' \(2\): not a number: '1,5' \(a decimal comma"):
        read_recording(path)
    path.write_text("t,op,pv\n0,1_0,2\n1,nan,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"line 2, column 'op' \(2\): not a number: '1_0'"):
        read_recording(path, fmt="csv")


def test_generic_time_that_repeats_or_jumps_is_refused(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("time,op,pv\n0,1,2\n1,1,2\n1,1,2\n2,1,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"t\.csv: line 4, column 'time' \(1\): time stamp '1' repeats line 3.*ts="):
        read_recording(path)
    assert len(read_recording(path, ts=1.0).recording) == 4        # ts= ignores the time column
    path.write_text("time,op,pv\n0,1,2\n1,1,2\n2,1,2\n9,1,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=r"line 5, column 'time' \(1\): gap in time: 7 s"):
        read_recording(path)


@pytest.mark.parametrize("kwargs, message", [
    ({"fmt": "xml"}, "fmt must be one of"),
    ({"ts": -1.0}, "ts must be a sample time"),
    ({"ts": math.nan}, "ts must be a sample time"),
    ({"decimal": ";"}, "decimal must be"),
    ({"skip": -1}, "skip must be"),
    ({"op_units": "V"}, "op_units must be one of"),
    ({"time": "t", "ts": 1.0}, "either time= .* or ts="),
])
def test_bad_arguments_are_refused(tmp_path, kwargs, message):
    path = tmp_path / "ok.csv"
    path.write_text("t,op,pv\n0,1,2\n1,1,2\n", encoding="utf-8")
    with pytest.raises(ReaderError, match=message):
        read_recording(path, **kwargs)


def test_empty_file_and_missing_file(tmp_path):
    (tmp_path / "empty.csv").write_bytes(b"\n\n")
    with pytest.raises(ReaderError, match=r"empty\.csv: line 1: the file is empty"):
        read_recording(tmp_path / "empty.csv")
    with pytest.raises(FileNotFoundError):
        read_recording(tmp_path / "nope.csv")
