"""Who may do what over OPC UA: users with hashed passwords, each with a role of the device's permission table.

Roles are the ones every interface shares (:mod:`valve_emulator.device.roles`): a **viewer** reads
everything and writes nothing; an **operator** also writes OP (in manual), SP and the mode; an
**instructor** writes every variable and calls the station's methods (Freeze, Run, SetSpeed, Snapshot,
Restore, InjectMalfunction); a custom role of ``device.roles`` writes the tags it lists. A write the role
may not make answers ``BadUserAccessDenied``; a method call of anyone but an instructor too.

The users file (names, hashed passwords, roles) is :mod:`valve_emulator.device.accounts`'s, shared with the
instructor station. Anonymous clients are operators, and only where the server allows anonymous access
(loopback without a users file).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.ua.ua_binary import struct_from_binary

from valve_emulator.device.accounts import authenticate
from valve_emulator.device.roles import OPERATOR, Role

__all__ = ["StationUser", "UsersFile", "RoleRuleset"]


@dataclass
class StationUser(User):
    """An asyncua :class:`User` that also carries its role of the permission table (asyncua's own role stays
    ``User``)."""

    station_role: Role = field(default=OPERATOR)


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
        role = None if password is None else authenticate(self.users, username, password)
        if role is None:
            return None
        return StationUser(role=UserRole.User, name=username, station_role=role)


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
    (:data:`ALARM_METHODS`: every role that writes something, not a viewer); no address-space editing at all."""

    def __init__(self) -> None:
        self._allowed = frozenset(ua.NodeId(t) for t in USER_TYPES)

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id not in self._allowed:
            return False
        session = user is None or user.role is not UserRole.Anonymous
        if action_type_id == _CALL:
            if _calls_only(body, ALARM_METHODS):   # acknowledging: any role that writes something
                return session and (not isinstance(user, StationUser) or user.station_role.writes)
            return isinstance(user, StationUser) and user.station_role.instructs
        return session
