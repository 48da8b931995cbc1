"""The device's register image in shared memory, for an OPC UA server in another process.

The device process owns an :class:`ImagePublisher`: whenever the image changes (after a tick's refresh, an
accepted write, an alarm word: :attr:`Device.image_listeners <valve_emulator.device.tick.Device>`) it copies the
image, the doubles the tick computed for the float32 quantities (PV, OP, MV, SP: served at full precision) and
the tick's counters into one ``multiprocessing.shared_memory`` block. That copy is all the tick pays for OPC
UA, however many clients subscribe.

The OPC UA process owns an :class:`ImageReader` on the same block. A sequence counter (odd while the publisher
writes) lets it take a consistent copy: it retries when the counter moved or was odd, so it never serves half
of one tick and half of the next. Both run single-threaded over x86's ordered stores; the counter is written
last and read first. The header says which tick the copy holds (``ticks``, ``sample_time``) and when the device
ran it (``wall time``: the time of the copy that first held that tick, not of a later write's): the
SourceTimestamp of every value sampled from it, whenever the OPC UA process samples it. :meth:`ImageReader.pinned`
keeps one copy for a whole block of reads (a chunk of a hand-off), so a chunk never mixes two ticks.

Layout: a header ``seq, ticks (uint64), sample_time, wall time (float64)``, then the image's bytes, then
``COMPUTED × n`` float64 (quantity-major).
"""

from __future__ import annotations

import contextlib
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing import resource_tracker, shared_memory
from typing import Any

import numpy as np

__all__ = ["COMPUTED", "SharedLayout", "ImagePublisher", "ImageReader", "TickImage"]

#: The quantities whose doubles are published beside the image (the image holds them as float32).
COMPUTED = ("pv", "op", "mv", "sp")
_HEADER = struct.Struct("<QQdd")
_SEQ = struct.Struct("<Q")


@dataclass(frozen=True)
class SharedLayout:
    """Where things are in the block: ``size`` image bytes for ``n`` loops."""

    size: int
    n: int

    @property
    def image_at(self) -> int:
        return _HEADER.size

    @property
    def doubles_at(self) -> int:
        return (_HEADER.size + self.size + 7) // 8 * 8

    @property
    def total(self) -> int:
        return self.doubles_at + 8 * len(COMPUTED) * self.n


@dataclass(frozen=True)
class TickImage:
    """One consistent copy of what the device published: the image, the doubles, the counters."""

    image: bytes
    computed: np.ndarray      # (len(COMPUTED), n) float64
    ticks: int
    sample_time: float
    wall_time: float
    seq: int


class ImagePublisher:
    """The device side: :meth:`publish` copies ``device``'s image into shared memory (see the module docstring).

    Counters: :attr:`copies` (one per publish)."""

    def __init__(self, device: Any) -> None:
        self.device = device
        self.layout = SharedLayout(size=len(device.image), n=int(device.bank.n))
        self.shm = shared_memory.SharedMemory(create=True, size=self.layout.total)
        self._image = np.ndarray(self.layout.size, dtype=np.uint8, buffer=self.shm.buf, offset=self.layout.image_at)
        self._doubles = np.ndarray((len(COMPUTED), self.layout.n), dtype=np.float64, buffer=self.shm.buf,
                                   offset=self.layout.doubles_at)
        self._no_controller = ~np.asarray(device.scaling.has_controller, dtype=bool)
        self._seq = 0
        self._tick: tuple[int, float] | None = None
        self._tick_wall = 0.0
        self.copies = 0

    @property
    def name(self) -> str:
        return self.shm.name

    def publish(self) -> None:
        """Copy the image and the tick's doubles; the counter is odd meanwhile."""
        device, bank, buf = self.device, self.device.bank, self.shm.buf
        self._seq += 1
        _SEQ.pack_into(buf, 0, self._seq)
        self._image[:] = np.frombuffer(device.image, dtype=np.uint8)
        for row, quantity in enumerate(COMPUTED):
            self._doubles[row] = getattr(bank, quantity)
        self._doubles[COMPUTED.index("sp"), self._no_controller] = 0.0   # a loop without controller reads SP 0
        self._seq += 1
        tick = (int(device.ticks), float(bank.sample_time))
        if tick != self._tick:   # a new tick (or a restored snapshot): its time; a write keeps the tick's
            self._tick, self._tick_wall = tick, time.time()
        _HEADER.pack_into(buf, 0, self._seq, tick[0], tick[1], self._tick_wall)
        self.copies += 1

    def close(self) -> None:
        self._image = self._doubles = None   # release the views before the block
        self.shm.close()
        self.shm.unlink()


class ImageReader:
    """The OPC UA side: :meth:`read` is the latest consistent :class:`TickImage`, copied only when it changed."""

    def __init__(self, name: str, layout: SharedLayout) -> None:
        self.layout = layout
        self.shm = shared_memory.SharedMemory(name=name)
        # the device process created the block and unlinks it; without this the reader's resource tracker would
        # unlink it too when this process ends (and warn of a leak)
        resource_tracker.unregister(self.shm._name, "shared_memory")
        self._last: TickImage | None = None
        self._pinned: TickImage | None = None

    def seq(self) -> int:
        return _SEQ.unpack_from(self.shm.buf, 0)[0]

    def read(self) -> TickImage:
        """The latest published image (the same object as long as nothing new was published); inside
        :meth:`pinned`, the one taken on entering it."""
        if self._pinned is not None:
            return self._pinned
        last = self._last
        if last is not None and self.seq() == last.seq:
            return last
        buf, lay = self.shm.buf, self.layout
        while True:
            seq, ticks, sample_time, wall = _HEADER.unpack_from(buf, 0)
            if seq % 2:
                time.sleep(0)
                continue
            image = bytes(buf[lay.image_at:lay.image_at + lay.size])
            computed = np.frombuffer(bytes(buf[lay.doubles_at:lay.total]), dtype=np.float64)
            if self.seq() == seq:
                self._last = TickImage(image, computed.reshape(len(COMPUTED), lay.n), ticks, sample_time, wall, seq)
                return self._last

    @contextlib.contextmanager
    def pinned(self) -> Iterator[TickImage]:
        """Every :meth:`read` inside the block answers the latest image as on entering it (one tick, however
        many the device runs meanwhile in its own process); nested blocks keep the outer one's."""
        if self._pinned is not None:
            yield self._pinned
            return
        self._pinned = self.read()
        try:
            yield self._pinned
        finally:
            self._pinned = None

    def close(self) -> None:
        self.shm.close()
