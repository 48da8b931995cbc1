"""Layer 3, reading recordings from files: the standard CSV, generic delimited exports, the DCS text export.

>>> from valve_emulator.io import read_recording                                  # doctest: +SKIP
>>> loaded = read_recording("FIC101.txt")                 # format detected; DCS: .MV is OP, .SV is SP
>>> loaded = read_recording("log.csv", op="OUT", pv="FLOW", ts=1.0, decimal=",")
>>> rec = loaded.recording           # a valve_emulator.sim.recording.Recording, op in %, longest AUTO segment
>>> print(loaded.report())           # columns used, excluded MANUAL segments, notes

Modules: :mod:`~valve_emulator.io.reader` (entry point and format detection), :mod:`~valve_emulator.io.dcs`,
:mod:`~valve_emulator.io.delimited`, :mod:`~valve_emulator.io.loaded` (result, units, segments, time axis),
:mod:`~valve_emulator.io.text` (decoding, cells, numbers, errors).
"""

from valve_emulator.io.loaded import DEFAULT_AUTO_VALUES, OP_UNITS, LoadedRecording
from valve_emulator.io.reader import FORMATS, detect_format, read_recording
from valve_emulator.io.text import ColumnSpec, ReaderError

__all__ = [
    "read_recording",
    "detect_format",
    "LoadedRecording",
    "ReaderError",
    "ColumnSpec",
    "FORMATS",
    "OP_UNITS",
    "DEFAULT_AUTO_VALUES",
]
