"""Roles, the one table of who may call what, and the listening policy for anonymous clients.

Roles are ordered: ``observer < operator < engineer < admin``; a role may do everything the roles below
it may. The table ``method_roles()`` maps (method family, method BrowseName) to the least role that may
call it (``method_roles()``: the rows of base OPC UA objects here, each companion's in its package).
Anything not in the table needs ``admin`` (deny by default). Pure: no OPC UA stack here.
"""

from __future__ import annotations

import functools
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
        try:
            return cls[name.strip().upper()]
        except KeyError:
            valid = ", ".join(r.label for r in cls)
            raise ValueError(f"unknown role {name!r} (valid: {valid})") from None

    @property
    def label(self) -> str:
        """The role as written in configuration and on the command line."""
        return self.name.lower()


class Family(str):
    """Where a method lives; the same BrowseName (Start, Stop, Open) means different things per family.

    The families of base OPC UA objects are here; each companion declares its own
    (``uacell.companion.Companion.type_hints``) together with the rows of the role table for them.
    """

    __slots__ = ()
    FILE: ClassVar[Family]
    DIRECTORY: ClassVar[Family]
    CONDITION: ClassVar[Family]
    SERVER: ClassVar[Family]

    def __repr__(self) -> str:
        return f"Family({str(self)!r})"


Family.FILE = Family("File")
Family.DIRECTORY = Family("Directory")
Family.CONDITION = Family("Condition")
Family.SERVER = Family("Server")

# ObjectType BrowseNames (and a few instance names) a dispatcher may pass as the hint; companions add theirs.
_TYPE_HINTS: dict[str, Family] = {
    "FileType": Family.FILE,
    "FileDirectoryType": Family.DIRECTORY,
    "ConditionType": Family.CONDITION,
    "AcknowledgeableConditionType": Family.CONDITION,
    "AlarmConditionType": Family.CONDITION,
    "ServerType": Family.SERVER,
}

OP, EN = Role.OPERATOR, Role.ENGINEER

# The rows for base OPC UA objects; ``method_roles()`` adds every companion's rows. FileType Open is
# listed for reading; opening for writing needs ENGINEER (see required_role's file_mode).
_BASE_ROLES: dict[tuple[Family, str], Role] = {
    **{(Family.FILE, m): OP for m in ("Open", "Read", "GetPosition", "SetPosition", "Close")},
    (Family.FILE, "Write"): EN,
    **{(Family.DIRECTORY, m): EN for m in ("CreateFile", "CreateDirectory", "Delete", "MoveOrCopy")},
    **{(Family.CONDITION, m): OP for m in ("Acknowledge", "Confirm", "AddComment")},
    # Alarm clients ask for the current conditions when they subscribe: as reading, anyone may.
    **{(Family.CONDITION, m): Role.OBSERVER for m in ("ConditionRefresh", "ConditionRefresh2")},
    **{(Family.CONDITION, m): EN for m in ("Enable", "Disable")},
    # OPC 10000-5 9.1: a client asks which monitored items its own subscription has (after a reconnect).
    (Family.SERVER, "GetMonitoredItems"): Role.OBSERVER,
}


@functools.cache
def method_roles() -> dict[tuple[Family, str], Role]:
    """THE table: (method family, method BrowseName) -> the least role that may call it."""
    from uacell.companion import companions

    table = dict(_BASE_ROLES)
    for companion in companions():
        table.update(companion.roles)
    return table


@functools.cache
def _type_hints() -> dict[str, Family]:
    from uacell.companion import companions

    hints = dict(_TYPE_HINTS)
    for companion in companions():
        hints.update(companion.type_hints)
    return hints


# Services other than Call. Attribute writes change configuration, hence engineer.
ACTION_ROLES: dict[str, Role] = {
    "read": Role.OBSERVER,
    "browse": Role.OBSERVER,
    "subscribe": Role.OBSERVER,
    "history_read": Role.OBSERVER,  # like read (decision 36)
    "write": EN,
}

# FileType Open mode bits (OPC 10000-5 FileType): Read=1, Write=2, EraseExisting=4, Append=8.
_FILE_WRITE_BITS = 0x2 | 0x4 | 0x8


def family_of(hint: str | Family) -> Family | None:
    """The method family for an ObjectType BrowseName or family name; None when unknown."""
    if isinstance(hint, Family):
        return hint
    name = hint.split(":", 1)[1] if ":" in hint else hint  # accept "3:TaskControlStateMachineType"
    hints = _type_hints()
    if name in hints:
        return hints[name]
    known = {family for family, _ in method_roles()}
    return Family(name) if name in known else None


def required_role(method: str, object_type_hint: str | Family, *, file_mode: int | None = None) -> Role:
    """The least role that may call ``method`` (BrowseName) on an object of the hinted family.

    Unknown methods need ADMIN. FileType ``Open`` needs ENGINEER unless ``file_mode`` is given and
    opens for reading only.
    """
    name = method.split(":", 1)[1] if ":" in method else method
    family = family_of(object_type_hint)
    if family is None:
        return Role.ADMIN
    if family is Family.FILE and name == "Open" and (file_mode is None or file_mode & _FILE_WRITE_BITS):
        return Role.ENGINEER
    return method_roles().get((family, name), Role.ADMIN)


def may_call(role: Role, method: str, object_type_hint: str | Family, *, file_mode: int | None = None) -> bool:
    """True when ``role`` may call ``method`` on an object of the hinted family."""
    return role >= required_role(method, object_type_hint, file_mode=file_mode)


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
