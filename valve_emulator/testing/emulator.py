""":class:`Emulator`: the valve emulator as a real Modbus TCP server on a free port, with a clock the test owns.

Two flavours of one class:

- ``async with Emulator() as emu:`` runs in the caller's event loop; :meth:`Emulator.advance` is a coroutine.
- ``with Emulator() as emu:`` runs its own event loop in a background thread; every method blocks until the
  emulator has done it, so plain (sync) test code and clients in other threads or processes can use it.

Clocks: ``"manual"`` (the default) runs no tick until :meth:`Emulator.advance` runs exactly
``round(seconds / dt)`` of them, back to back, answering requests between them. It is the device's lockstep
(``time_scale = 0``), so a client may also write the ``step`` register. ``"real"`` runs the device's real-time
tick at ``time_scale`` simulated seconds per second; :meth:`advance` then waits for that many ticks.

Nothing in a tick reads the wall clock: the same config and the same writes between the same ticks give the
same state, bit for bit. (A client that writes *while* :meth:`advance` runs makes the tick its write lands on
depend on the machine's speed; a test that wants bits to repeat writes between advances, or uses lockstep.)

State, faults and history, all in engineering units:

- :meth:`state` -- loop ``i``'s registers by name, decoded as a client would (``state(0)["pv"]``: PV in the
  loop's units; ``["time"]``: simulated s), and the status bits by name (``["seized"]``, ``["stuck"]``);
  :attr:`time`, :attr:`ticks`.
- :meth:`set` -- write registers by name with instructor rights, checked like a Modbus write.
- :meth:`inject` -- the instructor station's malfunctions (stiction, seize, load, noise, sensor faults,
  comm; ramps in simulated seconds).
- :meth:`snapshot` / :meth:`restore` -- the device's complete state.
- :attr:`traffic` -- every request the server answered (:class:`~valve_emulator.device.traffic.Request`).
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from valve_emulator.device.registers import (
    REGISTERS,
    Conversion,
    DataType,
    Register,
    RegisterAccessError,
    Status,
    from_words,
    register,
)
from valve_emulator.device.registers.codec import decode_value
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.testing import CLOCKS

__all__ = ["CLOCKS", "Emulator", "load_config", "status_bits"]
#: Wall time :meth:`Emulator.advance` runs ticks back to back before it lets waiting requests in.
_TURN = 0.002
#: Ticks per call of ``Device.advance`` inside a turn.
_BATCH = 500
_T = TypeVar("_T")


def load_config(config: Any = None) -> Any:
    """A ``ServerConfig`` from ``None`` (the embedded default device), a YAML path, a mapping (as in a YAML
    file) or a ``ServerConfig`` itself. ``ConfigError`` naming the file and key when it is wrong."""
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.runtime import load_server_or_default

    if config is None or isinstance(config, str | Path):
        return load_server_or_default(None if config is None else Path(config))
    if isinstance(config, Mapping):
        return server_from_mapping(config)
    if hasattr(config, "loops") and hasattr(config, "device"):
        return config
    raise TypeError(f"config must be None, a path, a mapping or a ServerConfig, got {type(config).__name__}")


class Emulator:
    """A running emulated device for a test (see the module docstring).

    Parameters
    ----------
    config : ``None`` (the embedded default device), a YAML path, a mapping or a ``ServerConfig``.
    clock : ``"manual"`` (ticks only in :meth:`advance`) or ``"real"``.
    time_scale : simulated seconds per wall second of the ``"real"`` clock (``math.inf``: back to back).
    host, port : where the Modbus TCP server listens; port 0 picks a free port (read :attr:`port`).
    instructor : allow instructor writes (``S``, ``J``, faults) over Modbus to every client.
    """

    def __init__(self, config: Any = None, *, clock: str = "manual", time_scale: float = 1.0,
                 host: str = "127.0.0.1", port: int = 0, instructor: bool = False) -> None:
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        if clock == "real" and not time_scale > 0:
            raise ValueError(f"time_scale must be > 0 for the real clock, got {time_scale!r}")
        cfg = load_config(config)
        if clock == "real" and cfg.device.lockstep:
            raise ValueError("clock 'real' with a config that sets device.lockstep: in lockstep the clock is "
                             "manual (leave clock at 'manual')")
        if instructor and not cfg.device.instructor_writes:
            from valve_emulator.device.runtime import with_device

            cfg = with_device(cfg, instructor_writes=True)
        self.config = cfg
        self.clock = clock
        self.host = host
        self._port = int(port)
        self._time_scale = 0.0 if clock == "manual" else float(time_scale)
        self.server: Any = None
        self._clients: list[Any] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    # --- what a test reads -----------------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The TCP port the server listens on (the free port it picked for ``port=0``)."""
        return self.server.port if self.server is not None else self._port

    @property
    def device(self) -> Any:
        """The :class:`~valve_emulator.device.tick.Device` behind the server."""
        self._require_running()
        return self.server.device

    @property
    def units(self) -> tuple[int, ...]:
        """The unit id of each loop, in loop order (``units[i]`` answers for ``state(i)``)."""
        return tuple(lp.device.unit for lp in self.config.loops)

    @property
    def dt(self) -> float:
        """Simulated seconds per tick (``device.tick``)."""
        return float(self.config.device.tick)

    @property
    def ticks(self) -> int:
        """Ticks run since the start (or since the restored snapshot was taken)."""
        return self.device.ticks

    @property
    def time(self) -> float:
        """Simulated time of the values the registers show now, s (exact; ``state(i)["time"]`` is float32)."""
        return float(self.device.bank.sample_time)

    @property
    def traffic(self) -> Any:
        """Every request the server has answered, oldest first
        (:class:`~valve_emulator.device.traffic.TrafficLog` of :class:`~valve_emulator.device.traffic.Request`)."""
        self._require_running()
        return self.server.traffic

    def state(self, loop: int = 0) -> dict[str, Any]:
        """Loop ``loop``'s registers by name, in engineering units, as a client reading them would decode them.

        ``pv``, ``sp``: PV units (the register's % of ``pv_range`` scaled back); ``op_pct``, ``mv_pct``,
        ``flow_pct``: %; ``op_ma``: mA; ``mode``: bool (auto); ``ti``: s (``inf``: no integral); ``status``,
        ``fault``, ``tick``, ``overruns``: integers; ``time`` and the ``*_f32`` registers: their float32 value.
        The controller's registers are absent on a loop without an internal controller. The bits of ``status``
        are there by name as well, each a bool: ``stuck``, ``moving``, ``sat_low``, ``sat_high``,
        ``controller``, ``auto``, ``seized`` (:func:`status_bits`).
        """
        return self._call(self._state, self._index(loop))

    def set(self, loop: int = 0, /, **values: Any) -> None:
        """Write registers of loop ``loop`` by name in engineering units (:meth:`state`'s units), in the order
        given, as an instructor would over Modbus: ``emu.set(0, mode=0, op_pct=40.0)``. A refused value raises
        the register map's ``RegisterError`` naming the register; the writes before it stay."""
        self._call(self._set, self._index(loop), values)

    def inject(self, kind: str, loop: int = 0, /, *, ramp: float = 0.0, **params: Any) -> dict[str, Any]:
        """Inject the instructor station's malfunction ``kind`` into loop ``loop``:
        ``emu.inject("stiction", S=8.0, J=4.0, ramp=60.0)``, ``emu.inject("load", flow=10.0)``,
        ``emu.inject("seize")``, ``emu.inject("comm", fault="no_response")``, ``emu.inject("clear")`` (kinds,
        parameters and the comm faults' names as scenario files write them: the one list,
        :data:`valve_emulator.device.malfunctions.KINDS`; docs/scenarios.md). Ramps run in
        simulated seconds. ``MalfunctionError`` naming the field when the request is wrong."""
        body = {"unit": self.units[self._index(loop)], "kind": kind, **params, "ramp": ramp}
        return self._call(self._inject, body)

    def snapshot(self, name: str = "test") -> Any:
        """The device's complete state now (a :class:`~valve_emulator.device.snapshots.Snapshot`)."""
        return self._call(lambda: self.device.snapshot(name))

    def restore(self, snapshot: Any) -> None:
        """Put a :meth:`snapshot` back: the device continues exactly as it did after taking it."""
        self._call(self.device.restore, snapshot)

    # --- the clock -------------------------------------------------------------------------------------

    def ticks_for(self, seconds: float) -> int:
        """``round(seconds / dt)``: the ticks :meth:`advance` runs for ``seconds`` of simulated time."""
        if not (isinstance(seconds, int | float) and math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"advance: seconds must be a finite number >= 0, got {seconds!r}")
        return round(seconds / self.dt)

    def advance(self, seconds: float) -> Any:
        """Run ``round(seconds / dt)`` ticks; returns the tick count after them.

        Manual clock: as fast as the machine allows, letting requests in every couple of milliseconds. Real
        clock: wait until the device's own tick has run them. Async flavour: a coroutine (``await
        emu.advance(10.0)``); sync flavour: blocks until done.
        """
        n = self.ticks_for(seconds)
        if self._thread is not None:
            return self._submit(self._advance(n))
        return self._advance(n)

    async def _advance(self, n: int) -> int:
        device = self.device
        target = device.ticks + n
        if not device.lockstep:
            return await device.wait_for_tick(target)
        loop = asyncio.get_running_loop()
        while True:
            turn_end = loop.time() + _TURN
            while device.ticks < target and loop.time() < turn_end:
                device.advance(min(_BATCH, target - device.ticks))
            if device.ticks >= target:
                return device.ticks
            await asyncio.sleep(0)   # requests waiting since the turn began are answered here

    # --- clients ---------------------------------------------------------------------------------------

    def client(self, **kwargs: Any) -> Any:
        """A pymodbus client for this server, closed with the emulator.

        Async flavour: an ``AsyncModbusTcpClient`` (``async with emu.client() as c:`` connects it); sync
        flavour: a ``ModbusTcpClient`` (``with emu.client() as c:``). ``kwargs`` go to its constructor
        (default ``timeout=2``, ``retries=0``).
        """
        from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient

        self._require_running()
        kwargs = {"timeout": 2, "retries": 0, **kwargs}
        cls = ModbusTcpClient if self._thread is not None else AsyncModbusTcpClient
        c = cls(self.host, port=self.port, **kwargs)
        self._clients.append(c)
        return c

    # --- lifecycle -------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the server and its clock in the running event loop (the async flavour's ``__aenter__``)."""
        from valve_emulator.device.server import EmulatorServer
        from valve_emulator.device.traffic import TrafficLog

        if self.server is not None:
            raise RuntimeError("this Emulator is already running")
        server = EmulatorServer(self.config, host=self.host, port=self._port, time_scale=self._time_scale)
        server.traffic = TrafficLog(lambda: server.device.bank.sample_time)
        await server.start()
        self.server = server

    async def stop(self) -> None:
        """Close the clients it handed out, the server (dropping connections) and its clock; idempotent."""
        server, self.server = self.server, None
        for c in self._clients:
            c.close()
        self._clients.clear()
        if server is not None:
            self._port = server.port
            await server.stop()

    async def __aenter__(self) -> Emulator:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()

    def __enter__(self) -> Emulator:
        """The sync flavour: start an event loop in a background thread and the emulator inside it."""
        if self._thread is not None or self.server is not None:
            raise RuntimeError("this Emulator is already running")
        loop = asyncio.new_event_loop()
        thread = threading.Thread(target=loop.run_forever, name="valve-emulator-testing", daemon=True)
        thread.start()
        self._loop, self._thread = loop, thread
        try:
            self._submit(self.start())
        except BaseException:
            self._shutdown_thread()
            raise
        return self

    def __exit__(self, *exc_info: Any) -> None:
        try:
            self._submit(self.stop())
        finally:
            self._shutdown_thread()

    def _shutdown_thread(self) -> None:
        """Stop the background loop once nothing runs in it any more, join the thread, close the loop."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        asyncio.run_coroutine_threadsafe(_cancel_rest(), loop).result(timeout=10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=10)
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()
        self._loop = self._thread = None

    # --- running things on the emulator's loop ----------------------------------------------------------

    def _submit(self, coro: Awaitable[_T]) -> _T:
        """Sync flavour: run ``coro`` on the background loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result()

    def _call(self, fn: Callable[..., _T], *args: Any) -> _T:
        """Run ``fn(*args)`` where the device lives: at once in the async flavour, on the background loop
        (between two requests, never inside a tick) in the sync one."""
        if self._thread is None or threading.current_thread() is self._thread:
            return fn(*args)

        async def call() -> _T:
            return fn(*args)

        return self._submit(call())

    def _require_running(self) -> None:
        if self.server is None:
            raise RuntimeError("the Emulator is not running: use it as `with Emulator() as emu:` or "
                               "`async with Emulator() as emu:`")

    def _index(self, loop: int) -> int:
        n = len(self.config.loops)
        if isinstance(loop, bool) or not isinstance(loop, int) or not -n <= loop < n:
            raise IndexError(f"loop {loop!r}: this emulator has loops 0..{n - 1} (units {list(self.units)})")
        return loop % n

    # --- the work itself (on the emulator's loop) -------------------------------------------------------

    def _state(self, index: int) -> dict[str, Any]:
        device = self.device
        start = int(device.offsets[index])
        words = [int.from_bytes(device.image[start + 2 * a:start + 2 * a + 2], "big")
                 for a in range(device.stride // 2)]
        controller = bool(device.scaling.has_controller[index])
        state = {reg.name: _engineering(reg, words, device.scaling, index) for reg in REGISTERS
                 if controller or reg.access.value != "RW-controller"}
        return {**state, **status_bits(state["status"])}

    def _set(self, index: int, values: Mapping[str, Any]) -> None:
        from valve_emulator.device.malfunctions import register_word

        device = self.device
        for name, value in values.items():
            reg = register(name)
            if reg.width != 1:
                raise RegisterAccessError(f"register {name} (holding {reg.address}) is read-only", register=name)
            if reg.conversion in (Conversion.FLAG, Conversion.BITS, Conversion.COUNTER):
                raw = int(value)
            elif reg.conversion is Conversion.LOOP_CURRENT:
                raw = round(float(value) * reg.scale)
            elif reg.zero_is_off and not (math.isfinite(value) and value > 0):
                raw = 0
            else:
                raw = register_word(name, float(value), device.scaling, index)
            device.write(index, reg.address, [raw], role=INSTRUCTOR)

    def _inject(self, body: dict[str, Any]) -> dict[str, Any]:
        from valve_emulator.device.malfunctions import parse_malfunction

        m = parse_malfunction(body, unit_index=self.device.unit_index, scaling=self.device.scaling)
        self.device.inject(m)
        return m.as_dict()


def status_bits(status: int) -> dict[str, bool]:
    """The ``status`` register's bits by name (``stuck``, ``moving``, ``sat_low``, ``sat_high``, ``controller``,
    ``auto``, ``seized``: :class:`~valve_emulator.device.registers.Status`), as :meth:`Emulator.state` shows them."""
    return {bit.name.lower(): bool(status & bit) for bit in Status}


def _engineering(reg: Register, words: list[int], scaling: Any, index: int) -> Any:
    """The engineering value register ``reg`` shows in a loop's ``words`` (see :meth:`Emulator.state`)."""
    at = words[reg.address:reg.address + reg.width]
    if reg.width == 2:
        value = from_words(at, reg.type, scaling.word_order)
        return value if reg.type is DataType.FLOAT32 else int(value)
    raw = int(from_words(at, reg.type))
    if reg.conversion is Conversion.LOOP_CURRENT:
        return raw / reg.scale
    return decode_value(reg, raw, scaling, index)


async def _cancel_rest() -> None:
    """Cancel and await whatever still runs on the background loop (a client's reconnect task, say)."""
    me = asyncio.current_task()
    rest = [t for t in asyncio.all_tasks() if t is not me]
    for task in rest:
        task.cancel()
    await asyncio.gather(*rest, return_exceptions=True)
