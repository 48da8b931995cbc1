"""Snapshots of a running device: named initial conditions, persisted as files, and the backtrack ring.

A :class:`Snapshot` holds the complete dynamic state of the device's loop bank
(:meth:`~valve_emulator.simulation.loop.LoopBank.state`: valve, plant and dead-time buffers, controller,
disturbance and noise generators, sample counter), the device's tick count and the running malfunction ramps,
so that restoring it makes the device continue sample for sample as it did after the save.

:class:`SnapshotStore` keeps named snapshots, in memory and -- with a directory -- as one ``NAME.npz`` file
each (numpy arrays plus a JSON header, no pickle: loading a file runs no code), so a lesson's initial
conditions survive a restart. A snapshot only fits a device built from the same configuration: the header
carries the unit ids, the number of loops and the tick, and :meth:`Device.restore
<valve_emulator.device.tick.Device.restore>` refuses a snapshot of another configuration.

:class:`BacktrackRing` takes a snapshot every ``interval`` simulated seconds and keeps the last ``size``
(commercial stations use 60 s to 600 s), so an instructor can rewind an exercise.
"""

from __future__ import annotations

import json
import re
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from valve_emulator.simulation.state import join, split

__all__ = ["Snapshot", "SnapshotError", "SnapshotNotFound", "SnapshotStore", "BacktrackRing", "check_name"]

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
_FORMAT = 1


class SnapshotError(ValueError):
    """A snapshot that cannot be stored or restored; ``field`` names what is wrong (``name``, ``units`` ...)."""

    def __init__(self, message: str, *, field: str = "name") -> None:
        super().__init__(message)
        self.field = field


class SnapshotNotFound(SnapshotError, KeyError):
    """No snapshot of that name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


def check_name(name: Any) -> str:
    """``name`` if it is a valid snapshot name (letters, digits, ``_ . -``, 1..64, no leading dot)."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise SnapshotError(f"field 'name': snapshot names are 1..64 letters, digits, '_', '.', '-', starting "
                            f"with a letter or digit; got {name!r}", field="name")
    return name


@dataclass(kw_only=True)
class Snapshot:
    """The state of a device at one tick (see the module docstring)."""

    name: str
    time: float                  # simulated time of the sample the device showed (s)
    ticks: int
    bank: dict[str, Any] = field(repr=False)
    device: dict[str, Any] = field(repr=False)   # tick count, malfunction ramps, configuration fingerprint
    created: float = field(default_factory=time.time)   # wall clock (s since the epoch)

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "time": self.time, "ticks": self.ticks, "created": self.created}

    def save(self, path: Path) -> None:
        """Write ``path`` (``.npz``): the bank's arrays plus one JSON header; atomic (write, then rename)."""
        arrays, text = split(self.bank)
        header = json.dumps({"format": _FORMAT, "name": self.name, "time": self.time, "ticks": self.ticks,
                             "created": self.created, "device": self.device, "bank": text})
        tmp = path.with_name(path.name + ".tmp")
        with tmp.open("wb") as f:
            np.savez(f, __header__=np.array(header), **{f"bank:{k}": v for k, v in arrays.items()})
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> Snapshot:
        """Read a file written by :meth:`save`; a broken file raises :class:`SnapshotError` naming it."""
        try:
            with np.load(path, allow_pickle=False) as data:
                header = json.loads(str(data["__header__"]))
                arrays = {k[5:]: data[k] for k in data.files if k.startswith("bank:")}
            if header.get("format") != _FORMAT:
                raise ValueError(f"format {header.get('format')!r}, expected {_FORMAT}")
            return cls(name=header["name"], time=float(header["time"]), ticks=int(header["ticks"]),
                       bank=join(arrays, header["bank"]), device=header["device"], created=header["created"])
        except (OSError, ValueError, KeyError) as exc:
            raise SnapshotError(f"{path}: not a readable snapshot ({exc})", field="file") from exc


class SnapshotStore:
    """Named snapshots, kept in memory and, with ``directory``, as ``NAME.npz`` files there."""

    def __init__(self, directory: Path | None = None) -> None:
        self.directory = directory
        self._snaps: dict[str, Snapshot] = {}
        if directory is not None:
            directory.mkdir(parents=True, exist_ok=True)
            for path in sorted(directory.glob("*.npz")):
                if _NAME.fullmatch(path.stem):
                    self._snaps[path.stem] = Snapshot.load(path)

    def __contains__(self, name: str) -> bool:
        return name in self._snaps

    def __iter__(self) -> Iterator[Snapshot]:
        return iter(sorted(self._snaps.values(), key=lambda s: s.created))

    def __len__(self) -> int:
        return len(self._snaps)

    def get(self, name: str) -> Snapshot:
        try:
            return self._snaps[name]
        except KeyError:
            raise SnapshotNotFound(f"no snapshot named {name!r} (have: {', '.join(sorted(self._snaps)) or 'none'})",
                                   field="name") from None

    def put(self, snap: Snapshot) -> None:
        check_name(snap.name)
        if self.directory is not None:
            snap.save(self.directory / f"{snap.name}.npz")
        self._snaps[snap.name] = snap

    def delete(self, name: str) -> None:
        self.get(name)
        if self.directory is not None:
            (self.directory / f"{name}.npz").unlink(missing_ok=True)
        del self._snaps[name]


class BacktrackRing:
    """A snapshot every ``interval`` simulated seconds, the last ``size`` kept (named ``bt-<seconds>``)."""

    def __init__(self, interval: float = 60.0, size: int = 30) -> None:
        if not (interval > 0) or size < 1:
            raise ValueError(f"backtrack interval must be > 0 s and size >= 1, got {interval!r}, {size!r}")
        self.interval, self.size = float(interval), int(size)
        self._ring: deque[Snapshot] = deque(maxlen=self.size)
        self._next = 0.0

    def due(self, t: float) -> bool:
        return t >= self._next

    def add(self, snap: Snapshot) -> None:
        self._ring.append(snap)
        self._next = snap.time + self.interval

    def reset(self, t: float) -> None:
        """After a restore to ``t``: forget the points after it, the next one an interval later."""
        while self._ring and self._ring[-1].time > t:
            self._ring.pop()
        self._next = t + self.interval

    def __iter__(self) -> Iterator[Snapshot]:
        return iter(self._ring)

    def get(self, name: str) -> Snapshot:
        for snap in self._ring:
            if snap.name == name:
                return snap
        raise SnapshotNotFound(f"no backtrack point named {name!r}", field="name")
