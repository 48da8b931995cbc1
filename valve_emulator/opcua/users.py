"""Who may do what over OPC UA: two roles, a users file with hashed passwords, and the rule asyncua enforces.

Roles are the instructor station's (``docs/station.md``): an **operator** reads everything and writes what a
Modbus client without instructor permission may write (OP in manual, SP, mode, tuning); an **instructor**
also writes the instructor variables (S, J, load, noise, fault) and calls the station's methods (Freeze,
Run, SetSpeed, Snapshot, Restore, InjectMalfunction).

The users file is YAML::

    users:
      alice: {role: instructor, password: "pbkdf2-sha256$600000$<salt hex>$<hash hex>"}
      bob:   {role: operator,   password: "pbkdf2-sha256$600000$..."}

with each password stored as PBKDF2-HMAC-SHA256 (``hashlib.pbkdf2_hmac``; NIST SP 800-132), made by
:func:`hash_password` (``valve-emulator certs --hash-password`` reads a password on standard input and
prints the line). A password is checked in constant time (:func:`hmac.compare_digest`). Anonymous clients
are operators, and only where the server allows anonymous access (loopback without a users file).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml
from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.ua.ua_binary import struct_from_binary

from valve_emulator.errors import UserError

__all__ = ["Role", "StationUser", "UsersFile", "UsersError", "RoleRuleset", "hash_password", "check_password",
           "load_users"]

#: PBKDF2 iterations of a new hash (OWASP's 2023 figure for PBKDF2-HMAC-SHA256).
ITERATIONS = 600_000
_SCHEME = "pbkdf2-sha256"


class Role(StrEnum):
    OPERATOR = "operator"
    INSTRUCTOR = "instructor"


class UsersError(UserError):
    """A users file that cannot be used: the message names the file and the key."""


@dataclass
class StationUser(User):
    """An asyncua :class:`User` that also carries the station role (asyncua's own role stays ``User``)."""

    station_role: Role = Role.OPERATOR

    @property
    def instructor(self) -> bool:
        return self.station_role is Role.INSTRUCTOR


def hash_password(password: str, *, iterations: int = ITERATIONS, salt: bytes | None = None) -> str:
    """The stored form of ``password``: ``pbkdf2-sha256$ITERATIONS$SALT$HASH`` (hex)."""
    salt = os.urandom(16) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"{_SCHEME}${iterations}${salt.hex()}${digest.hex()}"


def check_password(password: str, stored: str) -> bool:
    """Does ``password`` match the ``stored`` hash? Constant time in the hash comparison."""
    try:
        scheme, iterations, salt, digest = stored.split("$")
        if scheme != _SCHEME:
            return False
        expected = bytes.fromhex(digest)
        got = hashlib.pbkdf2_hmac("sha256", password.encode(), bytes.fromhex(salt), int(iterations))
    except ValueError:
        return False
    return hmac.compare_digest(got, expected)


@dataclass(frozen=True)
class UsersFile:
    """The users of a server: name -> (role, stored hash); ``anonymous`` says whether anonymous clients get
    the operator role."""

    users: Mapping[str, tuple[Role, str]]
    anonymous: bool = False

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> StationUser | None:
        """asyncua's user-manager call: the user for these credentials, or None (access denied)."""
        if username is None:
            if self.anonymous:
                return StationUser(role=UserRole.User, name="anonymous", station_role=Role.OPERATOR)
            return None
        entry = self.users.get(username)
        if entry is None or password is None or not check_password(password, entry[1]):
            return None
        return StationUser(role=UserRole.User, name=username, station_role=entry[0])


def load_users(path: Path | str) -> dict[str, tuple[Role, str]]:
    """Read a users file (see the module docstring); :class:`UsersError` names the file and key."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise UsersError(f"{path}: cannot read the users file: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise UsersError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, Mapping) or not isinstance(data.get("users"), Mapping) or not data["users"]:
        raise UsersError(f"{path}: key 'users' must map user names to {{role, password}}")
    users: dict[str, tuple[Role, str]] = {}
    for name, entry in data["users"].items():
        where = f"{path}: users.{name}"
        if not isinstance(entry, Mapping):
            raise UsersError(f"{where}: must be a mapping with 'role' and 'password'")
        unknown = sorted(set(entry) - {"role", "password"})
        if unknown:
            raise UsersError(f"{where}: unknown key(s) {', '.join(unknown)}")
        try:
            role = Role(entry.get("role"))
        except ValueError:
            raise UsersError(f"{where}.role: must be 'operator' or 'instructor', got {entry.get('role')!r}") from None
        stored = entry.get("password")
        if not isinstance(stored, str) or not stored.startswith(_SCHEME + "$") or stored.count("$") != 3:
            raise UsersError(f"{where}.password: must be a hash made by 'valve-emulator certs --hash-password' "
                             f"({_SCHEME}$...), never the password itself")
        users[str(name)] = (role, stored)
    return users


_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
#: The Alarms & Conditions methods every session may call: acknowledging an alarm is the operator's job, and a
#: client refreshes the conditions it shows when it subscribes (valve_emulator.opcua.alarms).
ALARM_METHODS = frozenset(ua.NodeId(m) for m in (ua.ObjectIds.AcknowledgeableConditionType_Acknowledge,
                                                 ua.ObjectIds.ConditionType_ConditionRefresh,
                                                 ua.ObjectIds.ConditionType_ConditionRefresh2))


def _calls_only(body: Any, methods: frozenset[ua.NodeId]) -> bool:
    """Does the (still encoded) CallRequest ``body`` call only ``methods``? Decoded from a copy: the server
    decodes the body itself afterwards."""
    try:
        params = struct_from_binary(ua.CallParameters, body.copy())
    except Exception:   # not decodable: the server's own decoding will refuse it
        return False
    calls = params.MethodsToCall or []
    return bool(calls) and all(c.MethodId in methods for c in calls)


class RoleRuleset(PermissionRuleset):
    """Which OPC UA services a session may use: the ordinary client services for everyone with a session;
    method calls (the station's instructor actions) only for instructors, except the alarm methods
    (:data:`ALARM_METHODS`); no address-space editing at all."""

    def __init__(self) -> None:
        self._allowed = frozenset(ua.NodeId(t) for t in USER_TYPES)

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id not in self._allowed:
            return False
        session = user is None or user.role is not UserRole.Anonymous
        if action_type_id == _CALL:
            if _calls_only(body, ALARM_METHODS):
                return session
            return isinstance(user, StationUser) and user.instructor
        return session
