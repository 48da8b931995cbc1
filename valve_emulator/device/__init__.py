"""Layer 4: the emulator as a Modbus TCP and Modbus RTU device.

- :mod:`~valve_emulator.device.registers`: the register map (every address and scaling) and the codec
  derived from it, including the compiled pass that encodes every loop each tick, pure.
- :mod:`~valve_emulator.device.image`: where each loop's registers live (units, 32-register blocks), pure.
- :mod:`~valve_emulator.device.tick`: :class:`Device`, the drift-free tick over a ``LoopBank``, pure asyncio.
- :mod:`~valve_emulator.device.server`: :class:`EmulatorServer`, the only module that imports pymodbus
  server-side code; imported lazily here so that ``registers`` and ``tick`` stay usable without it.
- :mod:`~valve_emulator.device.rtu`: Modbus RTU on a serial line and RTU frames over TCP;
  :mod:`~valve_emulator.device.comm`: communication faults on demand; :mod:`~valve_emulator.device.identity`:
  read device identification (FC43); the bit tables live with the registers
  (:mod:`~valve_emulator.device.registers.bits`).
"""

from typing import Any

from valve_emulator.device.registers import (
    N_REGISTERS,
    REGISTERS,
    RegisterAccessError,
    RegisterAddressError,
    RegisterError,
    RegisterValueError,
    Scaling,
    Status,
    format_registers,
    registers_table,
)
from valve_emulator.device.tick import Device, JitterBuffer

__all__ = [
    "N_REGISTERS",
    "REGISTERS",
    "Device",
    "EmulatorServer",
    "JitterBuffer",
    "RegisterAccessError",
    "RegisterAddressError",
    "RegisterError",
    "RegisterValueError",
    "Scaling",
    "Status",
    "format_registers",
    "registers_table",
]


def __getattr__(name: str) -> Any:
    if name == "EmulatorServer":
        from valve_emulator.device.server import EmulatorServer

        return EmulatorServer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
