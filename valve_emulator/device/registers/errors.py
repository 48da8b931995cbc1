"""What the register map refuses: :class:`RegisterError` and its kinds, each naming the register.

The errors are ``ValueError`` subclasses that carry the refused request as attributes; the Modbus adapter
(:mod:`valve_emulator.device.server`) alone translates them into exception codes.
"""

from __future__ import annotations

from valve_emulator.errors import UserError

__all__ = ["RegisterAccessError", "RegisterAddressError", "RegisterError", "RegisterValueError"]


class RegisterError(UserError):
    """A request the register map refuses; the message names the register.

    Attributes
    ----------
    register : name of the register concerned, when one is (``None`` for an address outside the map).
    """

    def __init__(self, message: str, *, register: str | None = None) -> None:
        super().__init__(message)
        self.register = register


class RegisterAddressError(RegisterError):
    """The addresses are not in the map (or not in the requested table).

    Attributes ``address`` and ``count``: the refused span (``None`` when not given).
    """

    def __init__(self, message: str, *, address: int | None = None, count: int | None = None) -> None:
        super().__init__(message)
        self.address, self.count = address, count


class RegisterAccessError(RegisterError):
    """The register exists but may not be written (read-only, no controller, no permission, auto mode)."""


class RegisterValueError(RegisterError):
    """The raw value is outside the register's range.

    Attributes ``value`` (the raw value, signed for ``int16``) and ``allowed`` (``(lo, hi)``).
    """

    def __init__(self, message: str, *, register: str | None = None, value: int | None = None,
                 allowed: tuple[int, int] | None = None) -> None:
        super().__init__(message, register=register)
        self.value, self.allowed = value, allowed
