"""Who may do what over OPC UA: users with hashed passwords, each with a role of the device's permission table.

Roles are the ones every interface shares (:mod:`valve_emulator.device.roles`): a **viewer** reads
everything and writes nothing; an **operator** also writes OP (in manual), SP and the mode; an
**instructor** writes every variable and calls the station's methods (Freeze, Run, SetSpeed, Snapshot,
Restore, InjectMalfunction); a custom role of ``device.roles`` writes the tags it lists. A write the role
may not make answers ``BadUserAccessDenied``; a method call of anyone but an instructor too.

The users file is YAML::

    users:
      alice: {role: instructor, password: "pbkdf2-sha256$600000$<salt hex>$<hash hex>"}
      bob:   {role: operator,   password: "pbkdf2-sha256$600000$..."}
      carol: {role: viewer,     password: "pbkdf2-sha256$600000$..."}

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole

from valve_emulator.device.roles import DEFAULT_ROLES, OPERATOR, Role, RoleTable
from valve_emulator.errors import UserError

__all__ = ["StationUser", "UsersFile", "UsersError", "RoleRuleset", "hash_password", "check_password",
           "load_users"]

#: PBKDF2 iterations of a new hash (OWASP's 2023 figure for PBKDF2-HMAC-SHA256).
ITERATIONS = 600_000
_SCHEME = "pbkdf2-sha256"


class UsersError(UserError):
    """A users file that cannot be used: the message names the file and the key."""


@dataclass
class StationUser(User):
    """An asyncua :class:`User` that also carries its role of the permission table (asyncua's own role stays
    ``User``)."""

    station_role: Role = field(default=OPERATOR)


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
                return StationUser(role=UserRole.User, name="anonymous", station_role=OPERATOR)
            return None
        entry = self.users.get(username)
        if entry is None or password is None or not check_password(password, entry[1]):
            return None
        return StationUser(role=UserRole.User, name=username, station_role=entry[0])


def load_users(path: Path | str, roles: RoleTable = DEFAULT_ROLES) -> dict[str, tuple[Role, str]]:
    """Read a users file (see the module docstring) whose roles are those of ``roles`` (the device's permission
    table: the built-in roles and ``device.roles``); :class:`UsersError` names the file and key."""
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
        role = roles.get(entry.get("role")) if isinstance(entry.get("role"), str) else None
        if role is None:
            raise UsersError(f"{where}.role: must be a role of the permission table ({roles.describe()}; "
                             f"device.roles adds custom roles), got {entry.get('role')!r}")
        stored = entry.get("password")
        if not isinstance(stored, str) or not stored.startswith(_SCHEME + "$") or stored.count("$") != 3:
            raise UsersError(f"{where}.password: must be a hash made by 'valve-emulator certs --hash-password' "
                             f"({_SCHEME}$...), never the password itself")
        users[str(name)] = (role, stored)
    return users


_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)


class RoleRuleset(PermissionRuleset):
    """Which OPC UA services a session may use: the ordinary client services for everyone with a session;
    method calls (the station's instructor actions) only for instructors; no address-space editing at all."""

    def __init__(self) -> None:
        self._allowed = frozenset(ua.NodeId(t) for t in USER_TYPES)

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id not in self._allowed:
            return False
        if action_type_id == _CALL:
            return isinstance(user, StationUser) and user.station_role.instructs
        return user is None or user.role is not UserRole.Anonymous
