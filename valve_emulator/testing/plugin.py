"""The pytest plugin of the testing kit, registered through the ``pytest11`` entry point (nothing to set up).

Fixtures
--------
``valve_emulator``
    A running :class:`~valve_emulator.testing.Emulator` on a free port of 127.0.0.1, stopped after the test.
    In a plain test it is the sync flavour (``valve_emulator.advance(10.0)`` blocks until done); in an
    ``async def`` test (pytest-asyncio) the async flavour, running in the test's event loop
    (``await valve_emulator.advance(10.0)``).
``valve_emulator_factory``
    Makes more of them, e.g. one per device of a plant: ``make(config=..., clock=..., time_scale=...)``
    returns a started emulator (``await make(...)`` in an async test); all are stopped after the test.
``valve_emulator_module``, ``valve_emulator_session``
    One running emulator (the sync flavour) shared by every test of a module, or of the whole run: started
    once, stopped after the last test. The tests see each other's writes and ticks; a test that needs a known
    state takes a :meth:`~valve_emulator.testing.Emulator.snapshot` and restores it.

Settings, each overriding the one before: the ini options ``valve_emulator_config`` (a YAML path, relative
to the ini file; default the embedded default device), ``valve_emulator_clock`` (``manual`` or ``real``;
default ``manual``) and ``valve_emulator_time_scale`` (default 1); the marker
``@pytest.mark.valve_emulator(config=..., clock=..., time_scale=..., instructor=...)`` on the test, its class or
module (a relative ``config`` path is read from the test file's folder; the module fixture sees the module's
marker, the session fixture only the ini options); the factory's arguments.

pytest-asyncio (the async flavour's runner) warns in every run of a project that leaves its ini option
``asyncio_default_fixture_loop_scope`` unset; the plugin sets it to ``function`` (pytest-asyncio's coming
default) in that case only, so that installing the kit adds no warning to a project's runs.
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from valve_emulator.testing import CLOCKS

_MARKER = "valve_emulator"
_SETTINGS = ("config", "clock", "time_scale", "instructor", "host", "port")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addini("valve_emulator_config", "valve_emulator fixture: YAML config of the emulated device "
                  "(default: the embedded default device)", default="")
    parser.addini("valve_emulator_clock", f"valve_emulator fixture: clock, one of {', '.join(CLOCKS)}",
                  default="manual")
    parser.addini("valve_emulator_time_scale", "valve_emulator fixture: simulated s per wall s of the real clock",
                  default="1.0")


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", f"{_MARKER}(config=None, clock='manual', time_scale=1.0, instructor=False): "
                                       "settings of the valve_emulator fixture (docs/testing.md)")
    _default_asyncio_loop_scope(config)


def _default_asyncio_loop_scope(config: pytest.Config) -> None:
    """``asyncio_default_fixture_loop_scope = function`` when pytest-asyncio is loaded and the project has not
    chosen one (see the module docstring). Runs before pytest-asyncio's own ``pytest_configure`` reads it."""
    name = "asyncio_default_fixture_loop_scope"
    try:
        chosen = config.getini(name)
    except ValueError:   # pytest-asyncio is not loaded
        return
    if not chosen:
        config._inicache[name] = "function"   # getini's cache: pytest has no public setter for an ini value


def settings(request: pytest.FixtureRequest, **overrides: Any) -> dict[str, Any]:
    """The emulator settings for ``request``'s test: ini options, then the marker, then ``overrides``."""
    ini = request.config
    chosen: dict[str, Any] = {"clock": ini.getini("valve_emulator_clock") or "manual"}
    path = ini.getini("valve_emulator_config")
    if path:
        root = Path(ini.inipath).parent if ini.inipath is not None else Path(ini.rootpath)
        chosen["config"] = root / path
    try:
        chosen["time_scale"] = float(ini.getini("valve_emulator_time_scale"))
    except ValueError:
        raise pytest.UsageError(f"ini option valve_emulator_time_scale must be a number, got "
                                f"{ini.getini('valve_emulator_time_scale')!r}") from None
    marker = request.node.get_closest_marker(_MARKER)
    if marker is not None:
        if marker.args:
            raise pytest.UsageError(f"@pytest.mark.{_MARKER} takes keyword arguments only ({', '.join(_SETTINGS)})")
        chosen.update(marker.kwargs)
        if isinstance(marker.kwargs.get("config"), str | Path):
            chosen["config"] = Path(request.node.path).parent / marker.kwargs["config"]
    chosen.update(overrides)
    unknown = sorted(set(chosen) - set(_SETTINGS))
    if unknown:
        raise pytest.UsageError(f"valve_emulator: unknown setting(s) {', '.join(unknown)}; known: "
                                f"{', '.join(_SETTINGS)}")
    return chosen


def _is_async(request: pytest.FixtureRequest) -> bool:
    return inspect.iscoroutinefunction(getattr(request.node, "obj", None))


@pytest.fixture
def valve_emulator_factory(request: pytest.FixtureRequest) -> Any:
    """Make started emulators (see the module docstring); the async flavour in an ``async def`` test."""
    return request.getfixturevalue("_valve_emulator_async_factory" if _is_async(request)
                                   else "_valve_emulator_sync_factory")


@pytest.fixture
def valve_emulator(request: pytest.FixtureRequest, valve_emulator_factory: Any) -> Any:
    """A running emulator with the settings of the ini options and the marker (see the module docstring)."""
    if _is_async(request):
        return request.getfixturevalue("_valve_emulator_async")
    return valve_emulator_factory()


@contextlib.contextmanager
def _started(request: pytest.FixtureRequest) -> Iterator[Callable[..., Any]]:
    """``make(**overrides)``: a started sync-flavour emulator with ``request``'s settings; all stopped on exit."""
    from valve_emulator.testing.emulator import Emulator

    running: list[Any] = []

    def make(**overrides: Any) -> Any:
        emu = Emulator(**settings(request, **overrides))
        emu.__enter__()
        running.append(emu)
        return emu

    try:
        yield make
    finally:
        for emu in reversed(running):
            emu.__exit__(None, None, None)


@pytest.fixture
def _valve_emulator_sync_factory(request: pytest.FixtureRequest) -> Any:
    with _started(request) as make:
        yield make


@pytest.fixture(scope="module")
def valve_emulator_module(request: pytest.FixtureRequest) -> Any:
    """One running emulator shared by the tests of a module (ini options, then the module's marker)."""
    with _started(request) as make:
        yield make()


@pytest.fixture(scope="session")
def valve_emulator_session(request: pytest.FixtureRequest) -> Any:
    """One running emulator shared by every test of the run (the ini options)."""
    with _started(request) as make:
        yield make()


try:
    import pytest_asyncio
except ImportError:   # pragma: no cover - async tests need pytest-asyncio anyway
    pytest_asyncio = None

if pytest_asyncio is not None:
    @pytest_asyncio.fixture
    async def _valve_emulator_async_factory(request: pytest.FixtureRequest) -> Any:
        from valve_emulator.testing.emulator import Emulator

        running: list[Any] = []

        async def make(**overrides: Any) -> Any:
            emu = Emulator(**settings(request, **overrides))
            await emu.start()
            running.append(emu)
            return emu

        yield make
        for emu in reversed(running):
            await emu.stop()

    @pytest_asyncio.fixture
    async def _valve_emulator_async(_valve_emulator_async_factory: Any) -> Any:
        return await _valve_emulator_async_factory()
