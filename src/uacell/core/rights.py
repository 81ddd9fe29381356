"""The one table of who may call what: the base rows (``uacell.core.roles``) and every companion's.

``RoleTable(companions)`` joins them; the composition root (``uacell.server.UacellServer``) makes
the table of the companions it serves and hands it to the method dispatcher and the security policy.
``method_roles`` maps (method family, method BrowseName) to the least role that may call it; anything
not in the table needs ``admin`` (deny by default). Pure: no OPC UA stack here.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TypeVar

from uacell.core.companion import Companion
from uacell.core.roles import BASE_ROLES, TYPE_HINTS, Family, Role

# FileType Open mode bits (OPC 10000-5 FileType): Read=1, Write=2, EraseExisting=4, Append=8.
_FILE_WRITE_BITS = 0x2 | 0x4 | 0x8

H = TypeVar("H")  # whatever the companions' functions receive of the server: not read here


class RoleTable:
    """THE table of the base rows and ``companions``' rows (``Companion.roles``, ``Companion.type_hints``)."""

    def __init__(self, companions: Iterable[Companion[H]]) -> None:
        table = dict(BASE_ROLES)
        hints = dict(TYPE_HINTS)
        for companion in companions:
            table.update(companion.roles)
            hints.update(companion.type_hints)
        self.method_roles: Mapping[tuple[Family, str], Role] = table
        self._hints: Mapping[str, Family] = hints
        self._families = frozenset(family for family, _ in table)

    def family_of(self, hint: str | Family) -> Family | None:
        """The method family for an ObjectType BrowseName or family name; None when unknown."""
        if isinstance(hint, Family):
            return hint
        name = hint.split(":", 1)[1] if ":" in hint else hint  # accept "3:TaskControlStateMachineType"
        if name in self._hints:
            return self._hints[name]
        return Family(name) if name in self._families else None

    def required_role(self, method: str, object_type_hint: str | Family, *, file_mode: int | None = None) -> Role:
        """The least role that may call ``method`` (BrowseName) on an object of the hinted family.

        Unknown methods need ADMIN. FileType ``Open`` needs ENGINEER unless ``file_mode`` is given and
        opens for reading only.
        """
        name = method.split(":", 1)[1] if ":" in method else method
        family = self.family_of(object_type_hint)
        if family is None:
            return Role.ADMIN
        if family is Family.FILE and name == "Open" and (file_mode is None or file_mode & _FILE_WRITE_BITS):
            return Role.ENGINEER
        return self.method_roles.get((family, name), Role.ADMIN)

    def may_call(
        self, role: Role, method: str, object_type_hint: str | Family, *, file_mode: int | None = None
    ) -> bool:
        """True when ``role`` may call ``method`` on an object of the hinted family."""
        return role >= self.required_role(method, object_type_hint, file_mode=file_mode)
