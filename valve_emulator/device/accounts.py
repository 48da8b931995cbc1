"""User accounts shared by OPC UA and the instructor station: a users file of names, hashed passwords, roles.

The users file is YAML::

    users:
      alice: {role: instructor, password: "pbkdf2-sha256$600000$<salt hex>$<hash hex>"}
      bob:   {role: operator,   password: "pbkdf2-sha256$600000$..."}
      carol: {role: viewer,     password: "pbkdf2-sha256$600000$..."}

Each role is one of the device's permission table (:mod:`~valve_emulator.device.roles`: ``viewer``,
``operator``, ``instructor``, or a custom role of ``device.roles``); a role outside it is refused when the
file is read, naming the file and the key. Each password is stored as PBKDF2-HMAC-SHA256
(``hashlib.pbkdf2_hmac``; NIST SP 800-132), made by :func:`hash_password` (``valve-emulator certs
--hash-password`` reads a password on standard input and prints the line), and checked in constant time
(:func:`hmac.compare_digest`). The same file serves ``serve --opcua-users`` and ``serve --web-users``.
"""

from __future__ import annotations

import hashlib
import hmac
import os
from collections.abc import Mapping
from pathlib import Path

import yaml

from valve_emulator.device.roles import DEFAULT_ROLES, Role, RoleTable
from valve_emulator.errors import UserError

__all__ = ["ITERATIONS", "UsersError", "authenticate", "check_password", "hash_password", "load_users"]

#: PBKDF2 iterations of a new hash (OWASP's 2023 figure for PBKDF2-HMAC-SHA256).
ITERATIONS = 600_000
_SCHEME = "pbkdf2-sha256"


class UsersError(UserError):
    """A users file that cannot be used: the message names the file and the key."""


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


def authenticate(users: Mapping[str, tuple[Role, str]], name: str, password: str) -> Role | None:
    """The role of user ``name`` if ``password`` is theirs; None otherwise (unknown user, wrong password)."""
    entry = users.get(name)
    if entry is None or not check_password(password, entry[1]):
        return None
    return entry[0]


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
