"""The top layer: the loopback testing kit, for tests of SCADA drivers, PLC programs and control logic.

- :class:`Emulator` -- the emulated device as a real Modbus TCP server on a free port, with a clock the test
  owns (``"manual"``: no tick until :meth:`Emulator.advance`), its state, faults, snapshots and the traffic it
  saw; an async context manager, or a sync one running its own event loop in a thread.
- :mod:`valve_emulator.testing.plugin` -- the pytest plugin (fixtures ``valve_emulator`` and
  ``valve_emulator_factory``, marker ``valve_emulator``), registered through the ``pytest11`` entry point.

The names below are imported when first used: pytest loads the plugin in every run of every project installed
beside this package, and the device (numba, pymodbus) should cost only the runs that use it.

Guide with examples: docs/testing.md.
"""

from typing import Any

#: The clocks an :class:`Emulator` can run on.
CLOCKS = ("manual", "real")

__all__ = ["CLOCKS", "Emulator", "Request", "TrafficLog", "load_config"]


def __getattr__(name: str) -> Any:
    if name in ("Emulator", "load_config"):
        from valve_emulator.testing import emulator

        return getattr(emulator, name)
    if name in ("Request", "TrafficLog"):
        from valve_emulator.device import traffic

        return getattr(traffic, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
