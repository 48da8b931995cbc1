"""The vocabulary of roles a configuration may name: the built-in roles, the writable tags, ``device.roles``.

A role is what a client may write, whatever interface it comes through (Modbus/TCP Security certificates,
OPC UA users, the instructor station; :mod:`valve_emulator.device.roles` holds the permission table). Three
roles are built in:

- ``viewer``: reads everything, writes nothing;
- ``operator``: writes OP, SP and the controller mode;
- ``instructor``: writes everything and uses the station's instructor actions.

A configuration adds its own roles as lists of writable tags, in the device section::

    device:
      roles:
        tuner: [kc, ti, td]          # may retune the controller, nothing else
        shift_lead: [op, sp, mode, kc, ti, td]

The tags are the names the OPC UA server gives the writable quantities (``op`` for ``op_pct`` and ``op_ma``,
``mode`` for the ``mode`` register and the ``auto`` coil, ``fault`` for the ``fault`` register and the
``seized`` coil) plus the unit registers ``comm_fault``, ``comm_delay_ms`` and the clock's ``step``. They are
named here, below the device, because a configuration names them (as :class:`~.schema.WordOrder` is); the
register map checks at import that its writable quantities are exactly these.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any, Final

from valve_emulator.errors import UserError

__all__ = ["BUILTIN_ROLES", "VIEWER", "OPERATOR", "INSTRUCTOR", "OPERATOR_TAGS", "WRITABLE_TAGS", "RoleConfigError",
           "custom_roles"]

VIEWER: Final = "viewer"
OPERATOR: Final = "operator"
INSTRUCTOR: Final = "instructor"
#: The roles every device knows; a configuration cannot redefine them.
BUILTIN_ROLES: Final = (VIEWER, OPERATOR, INSTRUCTOR)

#: Every tag a client may be allowed to write, in register-map order.
WRITABLE_TAGS: Final = ("op", "sp", "mode", "kc", "ti", "td", "S", "J", "load", "noise", "fault",
                        "comm_fault", "comm_delay_ms", "step")
#: What the built-in ``operator`` writes.
OPERATOR_TAGS: Final = ("op", "sp", "mode")

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,63}")


class RoleConfigError(UserError):
    """A ``device.roles`` entry that cannot be used: ``detail`` (with ``{key}`` for the key) and the ``key``.

    :class:`~valve_emulator.config.schema.DeviceConfig` turns it into its ``ConfigError`` (this module sits
    beside the schema, which imports it, so it cannot import the schema's error)."""

    def __init__(self, detail: str, *, key: str) -> None:
        self.detail, self.key = detail, key
        super().__init__(detail.replace("{key}", key))


def custom_roles(value: Any, key: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """Validate a ``device.roles`` section: ``{name: [tag, ...]}`` -> ``((name, tags), ...)`` in file order.

    A name is a plain word (a letter, then letters, digits, ``_ . -``; at most 64 characters) that is not a
    built-in role; a tag is one of :data:`WRITABLE_TAGS`, at most once. An empty list is allowed (a second
    name for a read-only client). :class:`RoleConfigError` names the key, e.g. ``roles.tuner[1]``."""
    if value is None:
        return ()
    if isinstance(value, tuple):   # already validated: a copy of a DeviceConfig (dataclasses.replace)
        value = dict(value)
    if not isinstance(value, Mapping):
        raise RoleConfigError("{key} must map role names to lists of writable tags, e.g. {tuner: [kc, ti, td]}",
                              key=key)
    roles = []
    for name, tags in value.items():
        where = f"{key}.{name}"
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise RoleConfigError(f"{{key}}: a role name is a plain word (letters, digits, _ . -), got {name!r}",
                                  key=where)
        if name in BUILTIN_ROLES:
            raise RoleConfigError(f"{{key}}: {name!r} is a built-in role ({', '.join(BUILTIN_ROLES)}); give the "
                                  f"custom role another name", key=where)
        roles.append((name, _tags(tags, where)))
    return tuple(roles)


def _tags(value: Any, key: str) -> tuple[str, ...]:
    if not isinstance(value, (list, tuple)):
        raise RoleConfigError(f"{{key}} must be a list of writable tags, got {value!r}", key=key)
    tags: list[str] = []
    for i, tag in enumerate(value):
        if not isinstance(tag, str) or tag not in WRITABLE_TAGS:
            raise RoleConfigError(f"{{key}}: {tag!r} is not a writable tag; the writable tags are "
                                  f"{', '.join(WRITABLE_TAGS)}", key=f"{key}[{i}]")
        if tag in tags:
            raise RoleConfigError(f"{{key}}: {tag!r} is listed twice", key=f"{key}[{i}]")
        tags.append(tag)
    return tuple(tags)
