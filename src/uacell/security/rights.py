"""The one table of who may call what: the base rows (``uacell.core.roles``) and every companion's.

``method_roles()`` maps (method family, method BrowseName) to the least role that may call it;
anything not in the table needs ``admin`` (deny by default). Pure: no OPC UA stack here.
"""

from __future__ import annotations

import functools

from uacell.catalog import companions
from uacell.core.roles import BASE_ROLES, TYPE_HINTS, Family, Role


@functools.cache
def method_roles() -> dict[tuple[Family, str], Role]:
    """THE table: (method family, method BrowseName) -> the least role that may call it."""
    table = dict(BASE_ROLES)
    for companion in companions():
        table.update(companion.roles)
    return table


@functools.cache
def _type_hints() -> dict[str, Family]:
    hints = dict(TYPE_HINTS)
    for companion in companions():
        hints.update(companion.type_hints)
    return hints


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
