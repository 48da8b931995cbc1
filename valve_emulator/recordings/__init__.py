"""Layer 2, recordings: the one home of :class:`Recording` and of every file a recording comes from or goes to.

>>> from valve_emulator.recordings import read_recording                           # doctest: +SKIP
>>> loaded = read_recording("FIC101.txt")       # format detected; DCS: .MV is OP, .SV is SP
>>> loaded = read_recording("log.csv", op="OUT", pv="FLOW", ts=1.0, decimal=",")
>>> rec = loaded.recording                      # a Recording, the longest AUTO segment
>>> print(loaded.report())                      # columns used, excluded MANUAL segments, notes

Modules: :mod:`~valve_emulator.recordings.recording` (the :class:`Recording` record, the standard CSV writer
and reader), :mod:`~valve_emulator.recordings.reader` (entry point and format detection),
:mod:`~valve_emulator.recordings.dcs`, :mod:`~valve_emulator.recordings.delimited` (the plant exports),
:mod:`~valve_emulator.recordings.loaded` (result, units, segments, time axis),
:mod:`~valve_emulator.recordings.text` (the one text parser: decoding, lines, cells),
:mod:`~valve_emulator.recordings.table` (numbers, times and columns read from the cells, with their line),
:mod:`~valve_emulator.recordings.errors`, :mod:`~valve_emulator.recordings.resample` (a jittered record onto a
uniform grid).
"""

from valve_emulator.recordings.errors import (
    ReaderError,
    RecordingError,
    RecordingWarning,
)
from valve_emulator.recordings.loaded import (
    DEFAULT_AUTO_VALUES,
    OP_UNITS,
    Format,
    LoadedRecording,
)
from valve_emulator.recordings.reader import FORMATS, detect_format, read_recording
from valve_emulator.recordings.recording import (
    CORE_COLUMNS,
    CsvRecordingWriter,
    Recording,
    read_csv,
    write_csv,
)
from valve_emulator.recordings.resample import MAX_GAP, regularize
from valve_emulator.recordings.table import ColumnSpec

__all__ = [
    "Recording",
    "RecordingError",
    "RecordingWarning",
    "CORE_COLUMNS",
    "read_csv",
    "write_csv",
    "CsvRecordingWriter",
    "read_recording",
    "detect_format",
    "regularize",
    "MAX_GAP",
    "LoadedRecording",
    "ReaderError",
    "ColumnSpec",
    "Format",
    "FORMATS",
    "OP_UNITS",
    "DEFAULT_AUTO_VALUES",
]
