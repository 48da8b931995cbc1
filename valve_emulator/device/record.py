"""A recorder inside the emulator process: one flushed CSV line per tick for each recorded loop.

``valve-emulator serve --record FILE.csv`` uses it. Each loop's file is the project's standard recording
(:mod:`valve_emulator.recordings.recording`): header ``t,sp,op,mv,pv`` then :data:`EXTRA_COLUMNS` (flow, the valve's
state, the instructor's stiction and faults, the tick), then one row per tick (or every ``every``-th) written by
:class:`~valve_emulator.recordings.recording.CsvRecordingWriter`, which emits every row with a single ``write``
followed by ``flush``. Once ``write`` has returned the line is in the kernel's page cache, so killing the
emulator (even ``SIGKILL``) loses at most the line being written, and
:func:`~valve_emulator.recordings.recording.read_csv` drops such a partial last line with a warning. (Surviving a
power cut as well needs ``fsync=True``: a disk round trip per row.)

Row ``k`` holds the state at sample instant ``t_k``, as :func:`~valve_emulator.simulation.loop.simulate_loop`
records it: ``t = bank.sample_time``, the time of the values ``sp, op, mv, pv, flow`` describe, written as
``k·dt`` like the offline recordings. ``tick`` is the device's tick counter.

Disk failures (full, read-only, removed) are reported once per file with the file name and the system's
reason, that file stops recording, and the device keeps ticking and serving: a recorder must never be the
reason the plant model stops.

The recorder is one of the device's :attr:`~valve_emulator.device.tick.Device.on_tick` callbacks, so it writes
each tick's row inside that tick, however the ticks are run: by the real-time task, back to back with
``time_scale = inf``, or many at once by :meth:`Device.advance` (a lockstep client's ``step`` write, the testing
kit's manual clock).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from valve_emulator.recordings.recording import CsvRecordingWriter

__all__ = ["EXTRA_COLUMNS", "TickRecorder", "recording_paths"]

EXTRA_COLUMNS = ("flow", "stuck", "S", "J", "load", "noise", "seized", "tick")
_log = logging.getLogger(__name__)


def recording_paths(path: str | Path, units: Sequence[int]) -> dict[int, Path]:
    """File per unit: ``path`` itself for one unit, else ``<stem>_u<unit:03d><suffix>`` next to it."""
    path = Path(path)
    if len(units) == 1:
        return {units[0]: path}
    return {u: path.with_name(f"{path.stem}_u{u:03d}{path.suffix}") for u in units}


class TickRecorder:
    """Record the loops of a :class:`~valve_emulator.device.tick.Device` tick by tick.

    Parameters
    ----------
    device : the running device.
    path : the CSV file (one unit) or the name the per-unit files derive from (:func:`recording_paths`).
    units : the units to record (default all, in device order); each must be one of ``device.units``.
        A device with several loops behind one unit (blocks) is refused with ``ValueError``.
    fsync : also ``os.fsync`` every row.
    every : record every ``every``-th tick (default 1: every tick).

    Use ``async with TickRecorder(device, path): ...`` or :meth:`start` / :meth:`stop`. Counters:
    :attr:`rows` (written), :attr:`failed` (unit -> reason for files that stopped).
    """

    def __init__(self, device: Any, path: str | Path, *, units: Sequence[int] | None = None,
                 fsync: bool = False, every: int = 1) -> None:
        if int(every) < 1:
            raise ValueError(f"every must be a whole number of ticks >= 1, got {every!r}")
        self.every = int(every)
        layout = getattr(device, "layout", None)
        if layout is not None and layout.blocked:
            raise ValueError("recording needs one loop per unit id; this device has several loops behind a unit "
                             "(fleet.loops_per_unit > 1)")
        units = tuple(device.units if units is None else units)
        unknown = [u for u in units if u not in device.unit_index]
        if not units or unknown or len(set(units)) != len(units):
            raise ValueError(f"record units must be distinct units of the device {list(device.units)}, "
                             f"got {list(units)}")
        self.device = device
        self.paths = recording_paths(path, units)
        self.fsync = bool(fsync)
        self.rows = 0
        self.failed: dict[int, str] = {}
        self._writers: dict[int, CsvRecordingWriter] = {}
        self._first = 0   # the tick count when recording started

    # --- lifecycle ----------------------------------------------------------------------------------

    async def start(self) -> None:
        """Create the files (a file that cannot be created is reported, not raised) and start recording."""
        for unit, path in self.paths.items():
            writer = CsvRecordingWriter(path, extra_columns=EXTRA_COLUMNS, fsync=self.fsync)
            try:
                writer.open()
            except OSError as exc:
                self._fail(unit, writer, exc)
                continue
            self._writers[unit] = writer
        if self._on_tick not in self.device.on_tick:
            self._first = self.device.ticks
            self.device.on_tick.append(self._on_tick)

    async def stop(self) -> None:
        """Stop recording and close the files (every written row is already flushed)."""
        if self._on_tick in self.device.on_tick:
            self.device.on_tick.remove(self._on_tick)
        for unit, writer in list(self._writers.items()):
            try:
                writer.close()
            except OSError as exc:   # closing flushes nothing new, but a vanished disk can still fail
                self._fail(unit, writer, exc)
        self._writers.clear()

    async def __aenter__(self) -> TickRecorder:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()

    # --- recording ----------------------------------------------------------------------------------

    def _on_tick(self, device: Any) -> None:
        if self._writers and (device.ticks - self._first) % self.every == 0:
            self.record()

    def record(self) -> None:
        """Append the current state of every recorded loop (one row per file)."""
        bank, index = self.device.bank, self.device.unit_index
        t = float(bank.sample_time)   # k·dt, as simulate_loop writes it
        sp, op, mv, pv, flow, stuck = bank.sp, bank.op, bank.mv, bank.pv, bank.flow, bank.stuck
        S, J, load, noise, seized = bank.S, bank.J, bank.load, bank.noise_std, bank.frozen
        tick = float(self.device.ticks)
        for unit, writer in list(self._writers.items()):
            i = index[unit]
            try:
                writer.write_row(t, sp[i], op[i], mv[i], pv[i], flow[i], float(stuck[i]), S[i], J[i], load[i],
                                 noise[i], float(seized[i]), tick)
                self.rows += 1
            except OSError as exc:
                self._fail(unit, writer, exc)
            except ValueError as exc:   # a non-finite op/pv or a repeated t: skip the row, keep the file
                _log.debug("unit %d: row at t=%s not recorded: %s", unit, t, exc)

    def _fail(self, unit: int, writer: CsvRecordingWriter, exc: OSError) -> None:
        """Report a disk failure once, stop that file, keep everything else running."""
        self._writers.pop(unit, None)
        reason = exc.strerror or str(exc)
        self.failed[unit] = reason
        _log.error("recording of unit %d to %s stopped after %d rows: %s (the device keeps running)",
                   unit, writer.path, writer.rows_written, reason)
        try:
            writer.close()
        except OSError:
            pass   # already reported; the file handle is released either way
