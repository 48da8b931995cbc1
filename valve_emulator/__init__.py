"""valve_emulator: a sticky control valve as a pure model, an offline loop and a Modbus TCP device."""

__version__ = "0.1.0"
