"""Enumeration values asyncua's decoder does not know, kept for the service to refuse.

asyncua decodes an enumeration by calling its class with the number, so a number the class lacks (a
BrowseDirection of 5) raises while the request is decoded and the whole request fails with
Bad_DecodingError. OPC 10000-4 gives each of these its own code, for the one operation that has it:
Bad_BrowseDirectionInvalid (5.8.2), Bad_TimestampsToReturnInvalid (Read 5.11.2, HistoryRead 5.11.3,
CreateMonitoredItems 5.13.2), Bad_MonitoringModeInvalid (5.13.2, 5.13.4), Bad_MonitoredItemFilterInvalid
for a DataChangeFilter's Trigger (7.22.2), Bad_FilterOperatorInvalid (7.7.4). For these enumerations the
class's ``_missing_`` now answers a stand-in member with the number (``unknown``), not a member of
the class, which the services' own checks then refuse (``known``: it equals no member).
"""

from __future__ import annotations

from enum import IntEnum

from asyncua import ua

from uacell.ua.door import patch

# The enumerations of requests whose unknown values the services answer with their own code.
LENIENT: tuple[type[IntEnum], ...] = (
    ua.BrowseDirection,
    ua.TimestampsToReturn,
    ua.MonitoringMode,
    ua.DataChangeTrigger,
    ua.FilterOperator,
)
_MODULE = "asyncua.ua.uaprotocol_auto"
_MEMBERS = {enum: frozenset(enum) for enum in LENIENT}


def _unknown(cls: type[IntEnum], value: object) -> IntEnum | None:
    """A stand-in for a number ``cls`` does not have (Enum's ``_missing_``); None for what is no number."""
    if not isinstance(value, int) or isinstance(value, bool):
        return None
    member = int.__new__(cls, value)
    member._name_ = f"unknown {value}"
    member._value_ = value
    return member


def known(value: object, enum: type[IntEnum]) -> bool:
    """Whether ``value`` is one of ``enum``'s members (a stand-in for an unknown number is not)."""
    return value in _MEMBERS[enum]


def install() -> None:
    for enum in LENIENT:
        patch(f"{_MODULE}.{enum.__name__}._missing_", classmethod(_unknown))


__all__ = ["LENIENT", "install", "known"]
