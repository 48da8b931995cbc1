"""What the OPC UA server needs of the device: one narrow interface, served in process or from another process.

:class:`~valve_emulator.opcua.server.OpcUaServer` (and its alarms and history) see the device only through a
:class:`DeviceSource`: the register image and the doubles behind its float32 registers, the tick counters,
waiting for a tick, a checked write, the PV alarms and the instructor station's actions. Two implement it:

- :class:`LocalSource`: the :class:`~valve_emulator.device.tick.Device` of this process (and its station), what
  the in-process server uses;
- :class:`~valve_emulator.opcua.remote.RemoteSource`: the same, in the OPC UA process, read from shared memory
  and forwarded over a socket to a :class:`LocalSource` in the device process
  (:mod:`valve_emulator.opcua.process`).

So there is one address-space builder, and a write or a method call is checked by the same code either way.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any, Protocol

from valve_emulator.device.alarms import AlarmChange
from valve_emulator.opcua.shared import TickImage

__all__ = ["DeviceSource", "LocalSource", "StationRefusal", "STATION_ACTIONS"]

#: The station's actions the OPC UA methods call, by name (each takes at most one argument).
STATION_ACTIONS = ("freeze", "run", "speed", "snapshot", "restore", "malfunction")


class StationRefusal(Exception):
    """The station refused an action (its ``StationError``): ``status`` 404 for an unknown snapshot, else 400."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message, status)
        self.status = status


class DeviceSource(Protocol):
    """The device as the OPC UA server sees it (see the module docstring)."""

    units: Sequence[int]
    offsets: Any
    scaling: Any
    dt: float
    has_station: bool
    has_alarms: bool
    #: called with every :class:`~valve_emulator.device.alarms.AlarmChange`
    alarm_listeners: list[Callable[[AlarmChange], None]]

    @property
    def image(self) -> bytes | bytearray: ...
    @property
    def ticks(self) -> int: ...
    @property
    def sample_time(self) -> float: ...
    @property
    def period(self) -> float: ...
    @property
    def tick_time(self) -> float | None: ...
    def sampling(self, tick: int | None = None) -> contextlib.AbstractContextManager[Any]: ...
    def computed(self, index: int, quantity: str) -> float | None: ...
    @property
    def snapshot(self) -> TickImage | None: ...
    def computed_column(self, snapshot: TickImage, quantity: str) -> Any: ...
    async def wait_for_tick(self, k: int) -> int: ...
    async def write(self, index: int, address: int, words: Sequence[int], role: Any) -> None: ...
    def raised_alarms(self) -> list[AlarmChange]: ...
    async def acknowledge_alarm(self, index: int) -> bool: ...
    async def station_action(self, action: str, argument: Any = None) -> Any: ...
    def paused(self) -> contextlib.AbstractAsyncContextManager[None]: ...


class LocalSource:
    """The :class:`DeviceSource` of a device in this process; ``station`` (a ``station.core.Station``) runs the
    station's actions and records acknowledgements (None: no station methods)."""

    def __init__(self, device: Any, station: Any = None) -> None:
        self.device, self.station = device, station
        self.units, self.offsets, self.scaling = device.units, device.offsets, device.scaling
        self.dt = float(device.bank.dt)
        self.has_station = station is not None
        self.has_alarms = device.alarms is not None
        self.alarm_listeners = device.alarms.listeners if device.alarms is not None else []

    @property
    def image(self) -> bytearray:
        return self.device.image

    @property
    def ticks(self) -> int:
        return self.device.ticks

    @property
    def sample_time(self) -> float:
        return float(self.device.bank.sample_time)

    @property
    def period(self) -> float:
        return self.device.period

    @property
    def tick_time(self) -> None:
        """When the current tick ran (POSIX seconds): not kept in this process (the tick pays nothing for it);
        the server stamps a tick when it first sees it (``TickClock``)."""
        return None

    def sampling(self, tick: int | None = None) -> contextlib.AbstractContextManager[Any]:
        """A block of reads of one tick: nothing to hold here, the tick runs in this event loop and a block that
        does not yield sees one tick (the current one, whatever ``tick``: no tick is kept past its own)."""
        return contextlib.nullcontext()

    def computed(self, index: int, quantity: str) -> float | None:
        """The double the last tick computed for a quantity the register image holds as float32."""
        bank = self.device.bank
        if quantity == "time":
            return float(bank.sample_time)
        if quantity == "sp" and not bank.has_controller[index]:
            return 0.0   # the controller's registers read 0 on a loop without one
        values = getattr(bank, quantity, None)
        return None if values is None else float(values[index])

    @property
    def snapshot(self) -> None:
        """What stands for the image and doubles served now, unchanged for as long as they are (None here: the
        device changes them in place, so nothing decoded from them may be kept)."""
        return None

    def computed_column(self, snapshot: TickImage, quantity: str) -> None:
        """Every loop's doubles of a quantity in ``snapshot``: only with a :attr:`snapshot` (none here)."""
        return None

    async def wait_for_tick(self, k: int) -> int:
        return await self.device.wait_for_tick(k)

    async def write(self, index: int, address: int, words: Sequence[int], role: Any) -> None:
        """``Device.write``: raises its ``RegisterError`` (nothing changed)."""
        self.device.write(index, address, words, role=role)

    def raised_alarms(self) -> list[AlarmChange]:
        """The alarms that need attention now (PV outside its limits, or not acknowledged)."""
        alarms = self.device.alarms
        if alarms is None:
            return []
        return [alarms.change(int(i)) for i in (alarms.words != 0).nonzero()[0].tolist()]

    async def acknowledge_alarm(self, index: int) -> bool:
        """Acknowledge loop ``index``'s PV alarm, through the station where there is one (the trainee's evaluation
        records it, ``who: opcua``); False when it needs no acknowledgement."""
        alarms = self.device.alarms
        if alarms is None or not alarms.change(index).unacked:
            return False
        unit = int(self.units[index])
        if self.station is not None and self.station.index_of(unit) == index:   # the station acks by unit id
            self.station.acknowledge(unit, who="opcua")
        else:
            alarms.acknowledge(index)
        return True

    async def station_action(self, action: str, argument: Any = None) -> Any:
        """Run the station's ``action`` (:data:`STATION_ACTIONS`); its refusal is a :class:`StationRefusal`."""
        st = self.station
        calls: dict[str, Callable[[], Any]] = {
            "freeze": st.freeze, "run": st.run,
            "speed": lambda: st.speed({"time_scale": argument}),
            "snapshot": lambda: st.save_snapshot({"name": argument}),
            "restore": lambda: st.restore_snapshot(argument),
            "malfunction": lambda: st.malfunction(argument),
        }
        try:
            result = calls[action]()
            if hasattr(result, "__await__"):
                result = await result
        except Exception as exc:
            if not hasattr(exc, "field"):   # not the station's refusal: a bug
                raise
            raise StationRefusal(str(exc), int(getattr(exc, "status", 400))) from None
        return result

    @contextlib.asynccontextmanager
    async def paused(self) -> AsyncIterator[None]:
        """Freeze a running device meanwhile (building a large address space keeps the event loop busy for
        seconds), so the build costs no overrun and the simulated time simply waits for it."""
        device = self.device
        pause = device.running and not device.frozen
        if pause:
            await device.freeze()
        try:
            yield
        finally:
            if pause:
                await device.resume()


def finite_period(source: DeviceSource) -> float:
    """The tick period in real seconds, or the tick (simulated) where time is frozen or as fast as possible."""
    return source.period if math.isfinite(source.period) else source.dt
