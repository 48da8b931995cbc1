"""valve_emulator: a sticky control valve as a pure model, an offline loop and a Modbus TCP device."""

from valve_emulator import _cache

_cache.configure()  # before any compiled kernel is defined: the cache lives in a user folder, not the package

__version__ = "0.1.0"
