"""Whether a monitored item reports a new value: OPC 10000-4 7.22.2 (DataChangeFilter) and 7.10
(DataChangeTrigger), as a pure function of the value last reported and the new one.

The comparison is with the *last value reported* (the standard's "last cached value": the last one
pushed to the item's queue), not with the value just before the new one. asyncua compares with the
value before, so a value drifting by less than the deadband at each step was never reported however
far it went; uacell's door (``uacell.ua.door.publishing``) asks this module instead.

- A change of the StatusCode is reported whatever the trigger and the deadband ("Deadband is
  ignored if the status of the data item changes").
- ``Status``: nothing else is reported.
- ``StatusValue`` (the default, no filter): a change of the value (its VariantType, its array
  dimensions or its payload). With an absolute deadband, a number is reported when it differs from
  the last value reported by more than the deadband, an array when its length changes or any
  element does so.
- ``StatusValueTimestamp``: also a change of the SourceTimestamp; with a deadband it behaves as
  ``StatusValue``.
- A floating-point NaN is reported once, when the value becomes NaN (NaN equals NaN here).
- A deadband on a value that is not a number (a string, a Boolean) compares for equality. A percent
  deadband needs the variable's EURange (OPC 10000-8) and is not applied: every change is reported,
  as asyncua did.
"""

from __future__ import annotations

from typing import Any

from asyncua import ua
from asyncua.ua import uaprotocol_auto

_ABSOLUTE = ua.DeadbandType.Absolute
_STATUS = ua.DataChangeTrigger.Status
_WITH_TIMESTAMP = ua.DataChangeTrigger.StatusValueTimestamp
# what a client's filter decodes to (``ua.DataChangeFilter`` is a subclass of it, for code that makes one)
_FILTER = uaprotocol_auto.DataChangeFilter


def reported(last: ua.DataValue | None, new: ua.DataValue, flt: object | None) -> bool:
    """Whether ``new`` is reported to a monitored item whose last reported value is ``last`` (None:
    nothing reported yet) and whose filter is ``flt`` (a DataChangeFilter, or None)."""
    if last is None:
        return True
    if _status(last) != _status(new):
        return True
    if not isinstance(flt, _FILTER):
        return _value_differs(last.Value, new.Value, None)
    if flt.Trigger == _STATUS:
        return False
    band = flt.DeadbandValue if flt.DeadbandType == _ABSOLUTE else None
    if _value_differs(last.Value, new.Value, band):
        return True
    return (
        band is None
        and flt.Trigger == _WITH_TIMESTAMP
        and (last.SourceTimestamp != new.SourceTimestamp or last.SourcePicoseconds != new.SourcePicoseconds)
    )


def _status(dv: ua.DataValue) -> int:
    return dv.StatusCode.value if dv.StatusCode is not None else 0


def _value_differs(last: ua.Variant | None, new: ua.Variant | None, band: float | None) -> bool:
    if last is None or new is None:
        return last is not new
    if last.VariantType != new.VariantType or last.Dimensions != new.Dimensions:
        return True
    return _differs(last.Value, new.Value, band)


def _differs(a: Any, b: Any, band: float | None) -> bool:
    if a == b:  # the common case, and equal arrays
        return False
    if isinstance(a, list) and isinstance(b, list):
        return len(a) != len(b) or any(_differs(x, y, band) for x, y in zip(a, b, strict=True))
    a_nan, b_nan = isinstance(a, float) and a != a, isinstance(b, float) and b != b
    if a_nan or b_nan:
        return a_nan != b_nan  # NaN stays NaN: reported once, when it began; and when it ends
    if band is not None and _is_number(a) and _is_number(b):
        return bool(abs(a - b) > band)
    return True


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)
