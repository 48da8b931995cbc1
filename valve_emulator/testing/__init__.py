"""The top layer: the loopback testing kit, for tests of SCADA drivers, PLC programs and control logic.

- :class:`Emulator` -- the emulated device as a real Modbus TCP server on a free port, with a clock the test
  owns (``"manual"``: no tick until :meth:`Emulator.advance`), its state, faults, snapshots and the traffic it
  saw; an async context manager, or a sync one running its own event loop in a thread.
- :mod:`valve_emulator.testing.plugin` -- the pytest plugin (fixtures ``valve_emulator`` and
  ``valve_emulator_factory``, marker ``valve_emulator``), registered through the ``pytest11`` entry point.

Guide with examples: docs/testing.md.
"""

from valve_emulator.device.traffic import Request, TrafficLog
from valve_emulator.testing.emulator import CLOCKS, Emulator, load_config

__all__ = ["CLOCKS", "Emulator", "Request", "TrafficLog", "load_config"]
