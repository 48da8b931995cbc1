"""Shared fixtures: async hygiene, a loop-bank test double, the mbpoll client, fake time.

Tests mirror the package (``tests/physics`` for ``valve_emulator/physics`` ...); ``tests/system`` holds the
end-to-end, robustness and scale tests, which are all marked ``slow``: ``pytest -m "not slow"`` is the quick
run while developing, the whole suite is what CI runs."""

from __future__ import annotations

import asyncio
import gc
import os
import sys
from collections.abc import Callable

import numpy as np
import pytest
from required import tool

_HERE = os.path.dirname(os.path.abspath(__file__))
# The testing kit's fixtures (valve_emulator, valve_emulator_factory): its pytest11 entry point loads them once the
# package is installed; naming the module here too keeps a checkout whose install predates the kit working.
# pytester runs the kit's plugin and the docs' examples in a scratch project.
pytest_plugins = ["valve_emulator.testing.plugin", "pytester"]


# Test modules all of whose tests assert wall-clock timing (tick rates, lateness and overruns while clients load
# the device). They are marked ``realtime``: .ci/run runs every other test in two processes (pytest-xdist) and then
# these on their own, so that no other test shares the machine's two cores with them. In a module that mixes them
# with tests on a manual clock (tests/system/test_device_closed_loop.py, test_robustness_flood.py), and elsewhere,
# a test that asserts wall-clock timing carries the marker itself.
_REALTIME = {
    "system/test_hostile_input.py",
    "system/test_robustness_fuzz.py",
    "system/test_clients_e2e.py",
}


def pytest_configure(config):
    """One numba thread per pytest-xdist worker when the workers already fill the cores (``.ci/run``'s two on
    two), as a plant-wide sweep's worker processes have (:mod:`valve_emulator.batch.pool`): two threads per
    worker would only queue behind the other worker (measured 2026-11-27: the first phase 477 s against 499-521 s
    with two). The diagnosis' documents are the same with one thread or two, and the threaded path keeps its own
    test (tests/diagnosis/test_kernel_threads.py sets two threads and compares a diagnosis bit for bit)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1 and workers >= len(os.sched_getaffinity(0)):
        import numba

        numba.set_num_threads(1)


def pytest_collection_modifyitems(items):
    for item in items:
        where = os.path.relpath(str(item.path), _HERE)
        if where.split(os.sep)[0] == "system":
            item.add_marker(pytest.mark.slow)
        if where.replace(os.sep, "/") in _REALTIME:
            item.add_marker(pytest.mark.realtime)


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session):
    """The shared draws the selected tests take as a parameter (tests/unseen_loops.py), in their order: a worker
    that waits for a draw another worker is diagnosing diagnoses one of these meanwhile."""
    unseen = sys.modules.get("unseen_loops")
    if unseen is None:   # no collected module uses them
        return
    params = (value for item in session.items for value in getattr(getattr(item, "callspec", None), "params",
                                                                   {}).values())
    unseen.NEEDED[:] = dict.fromkeys(value for value in params if isinstance(value, unseen.Draw))


@pytest.fixture(autouse=True)
def _runner_heap_frozen(request):
    """A wall-clock test is not charged for the test runner's own heap: once the whole suite is collected
    (about 2,750 tests and every module they import), a full garbage collection of this process takes 0.2-0.5 s,
    and one that falls inside a timed window stalls the device's event loop there (measured: one tick 0.33 s late
    in the OPC UA attack test, never with that file collected alone). Before a ``realtime`` test, what exists is
    collected once and moved out of the collector's sight (:func:`gc.freeze`); the test's own objects are
    collected as usual."""
    if request.node.get_closest_marker("realtime") is None:
        yield
        return
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


@pytest.fixture
async def no_task_leak():
    """Fail the test if it leaves asyncio tasks running (servers and tick tasks must be awaited on exit)."""
    before = set(asyncio.all_tasks())
    yield
    await asyncio.sleep(0)  # let just-cancelled tasks finish their cleanup
    leaked = [t for t in asyncio.all_tasks() - before if not t.done() and t is not asyncio.current_task()]
    for task in leaked:
        task.cancel()
    assert not leaked, f"tasks leaked: {[t.get_name() for t in leaked]}"


@pytest.fixture
def mbpoll() -> str:
    """Path of the mbpoll binary; missing: fail on CI (``CI`` set), skip elsewhere."""
    return tool("mbpoll", "apt-get install mbpoll")


class FakeClock:
    """Manual monotonic clock; ``sleep`` advances it by the requested delay plus an optional extra."""

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start
        self.extra: Callable[[], float] = lambda: 0.0   # lateness added to every sleep

    def __call__(self) -> float:
        return self.now

    async def sleep(self, delay: float) -> None:
        self.now += max(delay, 0.0) + self.extra()
        await asyncio.sleep(0)


@pytest.fixture
def fake_clock() -> FakeClock:
    return FakeClock()


class FakeLoopBank:
    """Test double of ``valve_emulator.simulation.loop.LoopBank`` for device tests that must not depend on physics.

    MV follows OP exactly (clipped to 0..100), flow = MV, PV a first-order lag of flow mapped onto
    ``pv_gain·(flow − 50)``; loops with a controller run a P controller around ``bias`` in auto. Every
    setter call is recorded in ``calls``; ``on_step`` callbacks run inside ``step`` (to inject slow steps).
    """

    def __init__(self, n: int, *, dt: float = 0.1, has_controller=False, pv_gain: float = 0.2) -> None:
        self.n, self.dt, self.t, self.k = n, dt, 0.0, 0
        self.has_controller = np.broadcast_to(np.asarray(has_controller, dtype=bool), (n,)).copy()
        self.auto = self.has_controller.copy()
        self.op_external = np.full(n, 50.0)
        self.manual_op = np.full(n, 50.0)
        self.op = np.full(n, 50.0)
        self.mv = self.op.copy()
        self.flow = self.op.copy()
        self.pv = np.zeros(n)
        self.sp = np.zeros(n)
        self.kc, self.ti, self.td = np.full(n, 0.2), np.full(n, 10.0), np.zeros(n)
        self.S, self.J = np.zeros(n), np.zeros(n)
        self.load, self.noise_std, self.frozen = np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)
        self.stuck = np.ones(n, dtype=bool)
        self.sat_low = np.zeros(n, dtype=bool)
        self.sat_high = np.zeros(n, dtype=bool)
        self.pv_gain = pv_gain
        self.calls: list[tuple] = []
        self.on_step: list[Callable[[FakeLoopBank], None]] = []

    @property
    def sample_time(self) -> float:
        return max(self.k - 1, 0) * self.dt

    @classmethod
    def for_config(cls, config, **kwargs) -> FakeLoopBank:
        ctl = [lp.controller is not None for lp in config.loops]
        return cls(len(config.loops), dt=config.device.tick, has_controller=ctl, **kwargs)

    def step(self) -> None:
        for hook in self.on_step:
            hook(self)
        auto = self.has_controller & self.auto
        ext = np.where(self.has_controller, self.manual_op, self.op_external)
        op = np.where(auto, 50.0 + self.kc * (self.sp - self.pv), ext)
        self.sat_low, self.sat_high = op < 0, op > 100
        mv = np.clip(op, 0.0, 100.0)
        self.stuck = mv == self.mv
        self.op, self.mv, self.flow = op, mv, mv.copy()
        self.pv = self.pv + 0.5 * (self.pv_gain * (self.flow - 50.0) - self.pv)
        self.k += 1
        self.t = self.k * self.dt

    def set_sp(self, i, value):
        self.calls.append(("sp", i, value))
        self.sp[i] = value

    def set_auto(self, i, flag):
        self.calls.append(("auto", i, flag))
        self.auto[i] = flag

    def set_manual_op(self, i, op):
        self.calls.append(("manual_op", i, op))
        self.manual_op[i] = op

    def set_tuning(self, i, kc=None, ti=None, td=None):
        self.calls.append(("tuning", i, kc, ti, td))
        for name, v in (("kc", kc), ("ti", ti), ("td", td)):
            if v is not None:
                getattr(self, name)[i] = v

    def set_valve(self, i, S=None, J=None):
        self.calls.append(("valve", i, S, J))
        if S is not None:
            self.S[i] = S
        if J is not None:
            self.J[i] = J


@pytest.fixture
def fake_bank_cls():
    """The :class:`FakeLoopBank` test double (a class, so tests can size and configure it)."""
    return FakeLoopBank


@pytest.fixture
async def client_for():
    """``await client_for(server)``: a connected pymodbus client of a running server (closed after the test)."""
    from pymodbus.client import AsyncModbusTcpClient

    clients = []

    async def connect(srv):
        client = AsyncModbusTcpClient("127.0.0.1", port=srv.port, timeout=2, retries=0)
        assert await client.connect()
        clients.append(client)
        return client

    yield connect
    for client in clients:
        client.close()
