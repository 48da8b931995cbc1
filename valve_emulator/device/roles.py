"""The permission table: what each role may write, the same on every interface.

One :class:`RoleTable` per device answers "may this client write that?" for Modbus/TCP Security (the role in
the client certificate, :mod:`~valve_emulator.device.tls`), OPC UA (the role of the user,
:mod:`valve_emulator.opcua.users`) and the instructor station (:mod:`valve_emulator.station.app`). Every write
then goes through :meth:`Device.write <valve_emulator.device.tick.Device.write>` with the client's
:class:`Role`, and the register codec refuses a register whose tag the role does not list (Modbus exception
0x02, OPC UA ``BadUserAccessDenied``, HTTP 403), exactly as it refuses a read-only register.

============== ==================================================== ==================================
role           writes                                               station instructor actions
============== ==================================================== ==================================
viewer         nothing                                              no
operator       op, sp, mode                                         no
instructor     every writable tag                                   yes (freeze, snapshots, faults)
custom         the tags listed in ``device.roles`` (config)         no
============== ==================================================== ==================================

A role name outside the table (a typo, ``readonly``) is no role at all: a certificate carrying it gets no
session, a users file naming it is refused at start. The plain Modbus port and the serial line have no
credentials: their clients get :data:`UNAUTHENTICATED` (every register not marked ``RW-instructor``), or
:data:`INSTRUCTOR` where ``device.instructor_writes``/``instructor_hosts`` allow it.

Tags are the names :mod:`valve_emulator.config.roles` lists (the OPC UA variable names: ``op`` covers
``op_pct`` and ``op_ma``, ``mode`` the ``mode`` register and the ``auto`` coil).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from valve_emulator.config.roles import (
    BUILTIN_ROLES,
    OPERATOR_TAGS,
    WRITABLE_TAGS,
)
from valve_emulator.config.roles import (
    INSTRUCTOR as INSTRUCTOR_NAME,
)
from valve_emulator.config.roles import (
    OPERATOR as OPERATOR_NAME,
)
from valve_emulator.config.roles import (
    VIEWER as VIEWER_NAME,
)
from valve_emulator.device.registers import CLOCK_REGISTERS, REGISTERS, RW_INSTRUCTOR, UNIT_REGISTERS, R

__all__ = ["Role", "RoleTable", "VIEWER", "OPERATOR", "INSTRUCTOR", "UNAUTHENTICATED", "BUILTIN_ROLES",
           "DEFAULT_ROLES", "tag_of"]

_ALL_REGISTERS = (*REGISTERS, *UNIT_REGISTERS, *CLOCK_REGISTERS)
#: quantity -> tag: the name of the quantity's first register, without ``_pct`` (the OPC UA variable name)
_TAG_OF: Mapping[str, str] = MappingProxyType(
    {q: next(r.name for r in _ALL_REGISTERS if r.quantity == q).removesuffix("_pct")
     for q in dict.fromkeys(r.quantity for r in _ALL_REGISTERS if r.access is not R)})
if set(_TAG_OF.values()) != set(WRITABLE_TAGS):   # the config's vocabulary and the register map must agree
    raise ImportError(f"config.roles.WRITABLE_TAGS {sorted(WRITABLE_TAGS)} differs from the register map's "
                      f"writable quantities {sorted(_TAG_OF.values())}")


def tag_of(quantity: str) -> str:
    """The tag a register quantity is written under (``auto`` -> ``mode``, ``op`` -> ``op``)."""
    return _TAG_OF.get(quantity, quantity)


@dataclass(frozen=True)
class Role:
    """A named set of writable tags; ``instructs``: may use the station's instructor actions (freeze, run,
    speed, snapshots, malfunctions, the OPC UA methods)."""

    name: str
    tags: frozenset[str]
    instructs: bool = False

    def may_write(self, quantity: str) -> bool:
        """May this role write the register quantity ``quantity`` (``op``, ``auto``, ``S``, ``step``, ...)?"""
        return tag_of(quantity) in self.tags

    @property
    def writes(self) -> bool:
        """Does it write anything at all?"""
        return bool(self.tags)

    def __str__(self) -> str:
        return self.name


VIEWER = Role(VIEWER_NAME, frozenset())
OPERATOR = Role(OPERATOR_NAME, frozenset(OPERATOR_TAGS))
INSTRUCTOR = Role(INSTRUCTOR_NAME, frozenset(WRITABLE_TAGS), instructs=True)
#: A client of the plain Modbus port or the serial line without instructor permission: every writable
#: register except the ``RW-instructor`` ones (what such a client has always written). Not in any table: no
#: certificate or user can name it.
UNAUTHENTICATED = Role("unauthenticated", frozenset(
    tag_of(r.quantity) for r in _ALL_REGISTERS if r.access is not R and r.access is not RW_INSTRUCTOR))


@dataclass(frozen=True)
class RoleTable:
    """The roles a device knows: the built-in ones and the configuration's ``device.roles``."""

    roles: Mapping[str, Role]

    @classmethod
    def of(cls, custom: Iterable[tuple[str, Iterable[str]]] = ()) -> RoleTable:
        """The built-in roles plus ``custom`` ``(name, tags)`` pairs (validated by the config:
        ``DeviceConfig.roles``)."""
        roles = {r.name: r for r in (VIEWER, OPERATOR, INSTRUCTOR)}
        for name, tags in custom:
            if name in roles:
                raise ValueError(f"role {name!r} is built in and cannot be redefined")
            unknown = sorted(set(tags) - set(WRITABLE_TAGS))
            if unknown:
                raise ValueError(f"role {name!r}: {', '.join(unknown)} not writable tags")
            roles[name] = Role(name, frozenset(tags))
        return cls(MappingProxyType(roles))

    @classmethod
    def from_config(cls, config: object) -> RoleTable:
        """The table of a ``ServerConfig`` or ``DeviceConfig`` (its ``device.roles``)."""
        device = getattr(config, "device", config)
        return cls.of(getattr(device, "roles", ()))

    def get(self, name: str | None) -> Role | None:
        """The role called ``name``; None when the table has none of that name."""
        return None if name is None else self.roles.get(name)

    def __contains__(self, name: object) -> bool:
        return name in self.roles

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.roles)

    def describe(self) -> str:
        """``viewer, operator, instructor, tuner`` -- for error messages."""
        return ", ".join(self.roles)


#: The table of a device without ``device.roles``.
DEFAULT_ROLES = RoleTable.of()
