"""Monitored items of values: which filters a client may ask for, and when a value is reported
(OPC 10000-4 7.22.2 DataChangeFilter and 7.10 DataChangeTrigger; OPC 10000-8 6.2 PercentDeadband).

``refusal`` checks a filter when a monitored item is created or modified, as the standards say:

- a DataChangeFilter on another attribute than Value, or an EventFilter on a Value, is
  Bad_FilterNotAllowed, as is a deadband on a variable whose DataType is not a Number; an event
  item without its EventFilter is Bad_MonitoredItemFilterInvalid (asyncua failed the request);
  a filter of another kind (an AggregateFilter) Bad_MonitoredItemFilterUnsupported;
- an unknown trigger or deadband type, or a negative deadband, is Bad_MonitoredItemFilterInvalid;
- a percent deadband outside 0 to 100, or on a variable without an EURange, is
  Bad_DeadbandFilterInvalid (OPC 10000-8 6.2 and its table of result codes);
- an IndexRange that does not parse is Bad_IndexRangeInvalid (``uacell.ua.numeric_range``). An item
  with an IndexRange reports the part of the value it names (the door cuts each value before this
  module compares it), so a change elsewhere in the array is not reported; a value with nothing
  there is reported as Bad_IndexRangeNoData (5.13.2.1).

``reported`` decides whether a new value is reported, as a pure function of the value last reported
and the new one. The comparison is with the *last value reported* (the standard's "last cached
value": the last one pushed to the item's queue), not with the value just before the new one.
asyncua compared with the value before, so a value drifting by less than the deadband at each step
was never reported however far it went; uacell's door (``uacell.ua.door.monitoring``) asks this
module instead.

- A change of the StatusCode is reported whatever the trigger and the deadband ("Deadband is
  ignored if the status of the data item changes").
- ``Status``: nothing else is reported.
- ``StatusValue`` (the default, no filter): a change of the value (its VariantType, its array
  dimensions or its payload). With a deadband, a number is reported when it differs from the last
  value reported by more than the deadband (absolute; or percent of the EURange's high minus low),
  an array when its length changes or any element does so.
- ``StatusValueTimestamp``: also a change of the SourceTimestamp; with a deadband it behaves as
  ``StatusValue``.
- A floating-point NaN is reported once, when the value becomes NaN (NaN equals NaN here).
"""

from __future__ import annotations

import math
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace
from asyncua.ua import uaprotocol_auto

from uacell.ua import content_filter, numeric_range, toolkit

_A = ua.AttributeIds
_NONE = ua.DeadbandType.None_
_ABSOLUTE = ua.DeadbandType.Absolute
_PERCENT = ua.DeadbandType.Percent
_NUMBER = ua.NodeId(ua.ObjectIds.Number)
_STATUS = ua.DataChangeTrigger.Status
_WITH_TIMESTAMP = ua.DataChangeTrigger.StatusValueTimestamp
# what a client's filter decodes to (``ua.DataChangeFilter`` is a subclass of it, for code that makes one)
_FILTER = uaprotocol_auto.DataChangeFilter
EVENT_FILTER = uaprotocol_auto.EventFilter
# the refusals (OPC 10000-4 7.22.2, OPC 10000-8 6.2)
_NOT_ALLOWED: int = ua.StatusCodes.BadFilterNotAllowed
_UNSUPPORTED: int = ua.StatusCodes.BadMonitoredItemFilterUnsupported
_INVALID: int = ua.StatusCodes.BadMonitoredItemFilterInvalid
_BAD_DEADBAND: int = ua.StatusCodes.BadDeadbandFilterInvalid


def reported(last: ua.DataValue | None, new: ua.DataValue, flt: object | None, eu_span: float | None = None) -> bool:
    """Whether ``new`` is reported to a monitored item whose last reported value is ``last`` (None:
    nothing reported yet) and whose filter is ``flt`` (a DataChangeFilter, or None); ``eu_span`` is
    the high minus the low of the variable's EURange, for a percent deadband (None: every change)."""
    if last is None:
        return True
    if _status(last) != _status(new):
        return True
    if not isinstance(flt, _FILTER):
        return _value_differs(last.Value, new.Value, None)
    if flt.Trigger == _STATUS:
        return False
    band = None
    if flt.DeadbandType == _ABSOLUTE:
        band = flt.DeadbandValue
    elif flt.DeadbandType == _PERCENT and eu_span is not None:
        band = flt.DeadbandValue / 100.0 * eu_span
    if _value_differs(last.Value, new.Value, band):
        return True
    return bool(
        flt.DeadbandType == _NONE
        and flt.Trigger == _WITH_TIMESTAMP
        and (last.SourceTimestamp != new.SourceTimestamp or last.SourcePicoseconds != new.SourcePicoseconds)
    )


def eu_span(aspace: AddressSpace, node: ua.NodeId) -> float | None:
    """The high minus the low of ``node``'s EURange property (OPC 10000-8 5.3.2), None without one."""
    prop = toolkit.find_child(aspace, node, "EURange")
    if prop is None:
        return None
    value = aspace.read_attribute_value(prop, _A.Value).Value
    if value is None or not isinstance(value.Value, ua.Range):
        return None
    return float(value.Value.High) - float(value.Value.Low)


LONGEST_SAMPLING = 3_600_000.0  # ms: the longest sampling interval served (an hour)


def revised_sampling_interval(requested: float, events: bool, publishing: float, minimum: float | None) -> float:
    """A monitored item's sampling interval in ms for a requested one (OPC 10000-4 5.13.1.2, 7.21): an
    event item's is 0; a negative or NaN request is the subscription's publishing interval; 0 is every
    change as it happens (uacell's values are written when they change, nothing is polled); never less
    than the request or the variable's MinimumSamplingInterval, at most ``LONGEST_SAMPLING``."""
    if events:
        return 0.0
    revised = publishing if math.isnan(requested) or requested < 0 else requested
    if minimum is not None and not math.isnan(minimum) and minimum > revised:
        revised = minimum
    return min(revised, LONGEST_SAMPLING)


class Sampler:
    """When a data item samples (OPC 10000-4 5.13.1.2: "the time between values returned to the Client
    shall be greater or equal to the sampling interval"): a change at least ``interval`` seconds after
    the item last sampled is sampled at once; one sooner waits for the next sample, when the latest
    value then is taken (sample and hold). Times in seconds on any monotonic clock."""

    __slots__ = ("interval", "last")

    def __init__(self, interval: float) -> None:
        self.interval = interval
        self.last: float | None = None  # when the item last sampled

    def wait(self, now: float) -> float:
        """0.0 when a change at ``now`` is sampled now, else the seconds until the next sample."""
        if self.interval <= 0 or self.last is None or now - self.last >= self.interval:
            return 0.0
        return self.last + self.interval - now


def revised_queue_size(requested: int, events: bool, largest: int) -> int:
    """A monitored item's queue size for a requested one (OPC 10000-4 7.21): a data item's 0 or 1 is 1
    (the latest value only, no queuing), an event item's 0 the server's default (its largest); a larger
    request at most ``largest``."""
    if requested <= (0 if events else 1):
        return largest if events else 1
    return min(requested, largest)


def refusal(aspace: AddressSpace, item: ua.ReadValueId, flt: object | None) -> int | None:
    """Why a monitored item of ``item`` may not have the filter ``flt`` (a StatusCode), or None. An
    IndexRange that does not parse is Bad_IndexRangeInvalid (OPC 10000-4 5.13.2.4)."""
    if item.IndexRange:
        try:
            numeric_range.parse(item.IndexRange)
        except numeric_range.RangeError as refused:
            return refused.code
    if isinstance(flt, ua.ExtensionObject) and flt.Body is None:
        flt = None  # a null ExtensionObject: no filter (what asyncua's client sends by default)
    attribute = item.AttributeId
    if attribute == _A.EventNotifier:
        node = aspace.get(item.NodeId)
        kind = node.attributes.get(_A.NodeClass) if node is not None else None
        if kind is not None and kind.value.Value.Value not in (ua.NodeClass.Object, ua.NodeClass.View):
            return int(ua.StatusCodes.BadAttributeIdInvalid)  # only objects and views have an EventNotifier
        if isinstance(flt, EVENT_FILTER):
            return content_filter.refusal(flt.WhereClause)
        return _INVALID if flt is None else _NOT_ALLOWED  # an event item needs its EventFilter
    if flt is None:
        return None
    if isinstance(flt, EVENT_FILTER):
        return _NOT_ALLOWED
    if not isinstance(flt, _FILTER):
        return _UNSUPPORTED  # an AggregateFilter, or a structure that is no filter
    if attribute != _A.Value:
        return _NOT_ALLOWED
    if flt.Trigger not in (0, 1, 2) or flt.DeadbandType not in (0, 1, 2):
        return _INVALID
    if flt.DeadbandType == _NONE:
        return None
    if not _is_number_type(aspace, item.NodeId):
        return _NOT_ALLOWED
    if flt.DeadbandType == _PERCENT:
        if not 0.0 <= flt.DeadbandValue <= 100.0 or eu_span(aspace, item.NodeId) is None:
            return _BAD_DEADBAND
    elif not flt.DeadbandValue >= 0.0:  # a negative absolute deadband (or NaN)
        return _INVALID
    return None


def filter_result(aspace: AddressSpace, item: ua.ReadValueId, flt: object | None) -> Any | None:
    """The FilterResult to answer for a monitored item (made or refused): an event item's
    EventFilterResult when a select clause or WhereClause element is wrong (decision 87), else None."""
    if item.AttributeId == _A.EventNotifier and isinstance(flt, EVENT_FILTER):
        return content_filter.event_filter_result(aspace, flt)
    return None


def _is_number_type(aspace: AddressSpace, node: ua.NodeId) -> bool:
    data = aspace.get(node)
    datatype = data.attributes.get(_A.DataType) if data is not None else None
    if datatype is None or datatype.value is None or datatype.value.Value is None:
        return False
    current: ua.NodeId | None = datatype.value.Value.Value
    for _ in range(32):  # the type tree is shallow; a loop in a broken model ends
        if current is None:
            return False
        if current == _NUMBER:
            return True
        current = toolkit.supertype(aspace, current)
    return False


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
