"""valve_emulator: a sticky control valve as a pure model, an offline loop and a Modbus TCP device.

The public surface, imported on first use so that ``import valve_emulator`` stays light:

>>> import valve_emulator as ve                                                      # doctest: +SKIP
>>> rec = ve.read_recording("FIC101.csv").recording
>>> d = ve.diagnose(rec, model=ve.load_loop("loop.yaml"))
>>> d.answer, d.fit_before, d.fit_after, d.predict(rec.op)

Every error about something the caller gave (a config, a recording, a flag) is a :class:`UserError`
(:class:`ConfigError`, :class:`RecordingError` ... derive from it); anything else that escapes is a bug.
"""

from __future__ import annotations

from valve_emulator import _cache, _lazy

_cache.configure()  # before any compiled kernel is defined: the cache lives in a user folder, not the package

__version__ = "0.1.0"

_EXPORTS = {
    "diagnose": "valve_emulator.diagnosis.api",
    "Diagnosis": "valve_emulator.diagnosis.report.diagnosis",
    "Answer": "valve_emulator.diagnosis.answers",
    "Strength": "valve_emulator.diagnosis.answers",
    "Recording": "valve_emulator.recordings",
    "RecordingError": "valve_emulator.recordings",
    "read_recording": "valve_emulator.recordings",
    "simulate_loop": "valve_emulator.simulation.loop",
    "load_loop": "valve_emulator.config",
    "LoopConfig": "valve_emulator.config",
    "ConfigError": "valve_emulator.config",
    "UserError": "valve_emulator.errors",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


__getattr__ = _lazy.exports(__name__, _EXPORTS, globals())


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
