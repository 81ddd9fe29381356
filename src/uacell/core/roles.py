"""Roles, method families, the rows of base OPC UA objects, and the listening policy for anonymous clients.

Roles are ordered: ``observer < operator < engineer < admin``; a role may do everything the roles below
it may. ``BASE_ROLES`` holds the rows of the role table for base OPC UA objects; ``uacell.core.rights``
joins them with each companion's rows into the one table. Pure and a leaf: no OPC UA stack, nothing
of uacell imported.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import ClassVar


class Role(IntEnum):
    """A user's role; a higher value may do everything a lower one may."""

    OBSERVER = 0
    OPERATOR = 1
    ENGINEER = 2
    ADMIN = 3

    @classmethod
    def parse(cls, name: str | Role) -> Role:
        """``"operator"`` (any case) -> ``Role.OPERATOR``; ValueError names the valid roles."""
        if isinstance(name, Role):
            return name
        role = _PARSED.get(name)
        if role is not None:
            return role
        try:
            role = cls[name.strip().upper()]
        except KeyError:
            valid = ", ".join(r.label for r in cls)
            raise ValueError(f"unknown role {name!r} (valid: {valid})") from None
        if len(_PARSED) < 64:  # the spellings configurations use; a call parses its caller's role
            _PARSED[name] = role
        return role

    @property
    def label(self) -> str:
        """The role as written in configuration and on the command line."""
        return self.name.lower()


_PARSED: dict[str, Role] = {}


class Family(str):
    """Where a method lives; the same BrowseName (Start, Stop, Open) means different things per family.

    The families of base OPC UA objects are here; each companion declares its own
    (``uacell.core.companion.Companion.type_hints``) together with the rows of the role table for them.
    """

    __slots__ = ()
    FILE: ClassVar[Family]
    DIRECTORY: ClassVar[Family]
    CONDITION: ClassVar[Family]
    SERVER: ClassVar[Family]
    SERVER_CONFIGURATION: ClassVar[Family]
    TRUST_LIST: ClassVar[Family]

    def __repr__(self) -> str:
        return f"Family({str(self)!r})"


Family.FILE = Family("File")
Family.DIRECTORY = Family("Directory")
Family.CONDITION = Family("Condition")
Family.SERVER = Family("Server")
Family.SERVER_CONFIGURATION = Family("ServerConfiguration")
Family.TRUST_LIST = Family("TrustList")

# ObjectType BrowseNames (and a few instance names) a dispatcher may pass as the hint; companions add theirs.
TYPE_HINTS: dict[str, Family] = {
    "FileType": Family.FILE,
    "FileDirectoryType": Family.DIRECTORY,
    "ConditionType": Family.CONDITION,
    "AcknowledgeableConditionType": Family.CONDITION,
    "AlarmConditionType": Family.CONDITION,
    "ServerType": Family.SERVER,
    "ServerConfigurationType": Family.SERVER_CONFIGURATION,
    "TrustListType": Family.TRUST_LIST,
}

OP, EN = Role.OPERATOR, Role.ENGINEER

# The rows for base OPC UA objects; ``method_roles()`` adds every companion's rows. FileType Open is
# listed for reading; opening for writing needs ENGINEER (see required_role's file_mode).
BASE_ROLES: dict[tuple[Family, str], Role] = {
    **{(Family.FILE, m): OP for m in ("Open", "Read", "GetPosition", "SetPosition", "Close")},
    (Family.FILE, "Write"): EN,
    **{(Family.DIRECTORY, m): EN for m in ("CreateFile", "CreateDirectory", "Delete", "MoveOrCopy")},
    **{(Family.CONDITION, m): OP for m in ("Acknowledge", "Confirm", "AddComment")},
    # Alarm clients ask for the current conditions when they subscribe: as reading, anyone may.
    **{(Family.CONDITION, m): Role.OBSERVER for m in ("ConditionRefresh", "ConditionRefresh2")},
    **{(Family.CONDITION, m): EN for m in ("Enable", "Disable")},
    # OPC 10000-5 9.1, 9.3: a client asks which monitored items its own subscription has, or for their
    # current values again (after a reconnect).
    **{(Family.SERVER, m): Role.OBSERVER for m in ("GetMonitoredItems", "ResendData")},
    # OPC 10000-12 7.10: the server's certificate managed by a GDS (SecurityAdmin; decision 96)
    **{
        (Family.SERVER_CONFIGURATION, m): Role.ADMIN
        for m in ("CreateSigningRequest", "UpdateCertificate", "ApplyChanges", "GetRejectedList")
    },
    **{(Family.TRUST_LIST, m): Role.ADMIN for m in ("AddCertificate", "RemoveCertificate")},
}


# Services other than Call. Attribute writes change configuration, hence engineer.
ACTION_ROLES: dict[str, Role] = {
    "read": Role.OBSERVER,
    "browse": Role.OBSERVER,
    "subscribe": Role.OBSERVER,
    "history_read": Role.OBSERVER,  # like read (decision 36)
    "write": EN,
}


def may(role: Role, action: str) -> bool:
    """True when ``role`` may perform a non-Call service action (read, browse, subscribe, history_read,
    write)."""
    return role >= ACTION_ROLES.get(action, Role.ADMIN)


# Listening policy -----------------------------------------------------------------------------------


def is_loopback(host: str) -> bool:
    """True for loopback addresses and the name ``localhost``; wildcard and other names are not."""
    h = host.strip().strip("[]").lower().rstrip(".")
    if h == "localhost" or h.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False  # a host name might resolve anywhere: treat it as the plant network


def _all_loopback(hosts: Iterable[str]) -> bool:
    hosts = list(hosts)
    return bool(hosts) and all(is_loopback(h) for h in hosts)


def anonymous_role(listening_hosts: Iterable[str], configured: Role | None = None) -> Role:
    """OPERATOR when every listening host is loopback, OBSERVER otherwise; ``configured`` wins."""
    if configured is not None:
        return configured
    return Role.OPERATOR if _all_loopback(listening_hosts) else Role.OBSERVER


def none_security_allowed(listening_hosts: Iterable[str], configured: bool | None = None) -> bool:
    """SecurityPolicy None is offered on loopback only, unless ``configured`` says otherwise."""
    if configured is not None:
        return configured
    return _all_loopback(listening_hosts)


@dataclass(frozen=True)
class ListeningPolicy:
    """What the server offers for a set of listening hosts; ``warnings`` are for the start-up log."""

    anonymous_role: Role
    none_security: bool
    warnings: list[str] = field(default_factory=list)


def listening_policy(
    listening_hosts: Iterable[str],
    anonymous: Role | None = None,
    allow_none_security: bool | None = None,
) -> ListeningPolicy:
    """Apply the listening policy; a configured value that differs from the default yields a warning."""
    hosts = list(listening_hosts)
    default_role = anonymous_role(hosts)
    default_none = none_security_allowed(hosts)
    role = anonymous_role(hosts, anonymous)
    none = none_security_allowed(hosts, allow_none_security)
    where = "loopback only" if _all_loopback(hosts) else "a non-loopback address"
    warnings = []
    if role != default_role:
        warnings.append(
            f"configuration gives anonymous clients the role {role.label} "
            f"(default {default_role.label} while listening on {where})"
        )
    if none != default_none:
        state = "offered" if none else "not offered"
        warnings.append(f"configuration: SecurityPolicy None is {state} while listening on {where}")
    return ListeningPolicy(role, none, warnings)
