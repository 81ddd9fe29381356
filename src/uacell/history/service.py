"""HistoryRead (OPC 10000-11) over the history store, in place of asyncua's HistoryManager.

What is kept: values of the variables ``historize_value`` names (taken from the address space's
data-change callbacks, so every written value counts, none is sampled) and the events fired through
the notifiers ``historize_events`` names (taken where asyncua hands events to subscriptions).
docs/history.md says what each request answers.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import struct
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.server.internal_server import InternalServer
from asyncua.ua.ua_binary import Primitives, variant_from_binary, variant_to_binary

from uacell.history import at_time, raw
from uacell.history.backends import EVENT, VALUE, Query, Sample
from uacell.history.event_filter import HistoryError
from uacell.history.processed import AGGREGATES, Interval, aggregate, intervals
from uacell.history.slices import Slices
from uacell.history.store import ContinuationPointInvalid, HistoryStore, first_line
from uacell.ua import door, numeric_range
from uacell.ua.content_filter import FilterError, WhereClause
from uacell.ua.context import caller_of, current_caller
from uacell.ua.door import enums
from uacell.ua.event_tap import EventTap

log = logging.getLogger(__name__)

_SC = ua.StatusCodes
_A = ua.AttributeIds
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_US = timedelta(microseconds=1)
_AT_TIME = -2  # the mark of a ReadAtTime continuation point (a raw read's names a sample's seq)


def to_micros(t: datetime) -> int:
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return (t - _EPOCH) // _US


def from_micros(us: int) -> datetime:
    return _EPOCH + us * _US


def _unspecified(t: datetime | None) -> bool:
    return t is None or t.year <= 1601


def node_key(node: ua.NodeId) -> str:
    return str(node.to_string())


async def mark_historizing(aspace: Any, node: ua.NodeId) -> None:
    """Historizing true, and the HistoryRead bit in AccessLevel and UserAccessLevel, each written
    only where it is not so yet: ``add_configurations`` marks the kept variables before the
    address-space snapshot is taken, so that a restart finds them marked."""
    bit = ua.AccessLevel.HistoryRead.mask
    for attr in (_A.AccessLevel, _A.UserAccessLevel):
        level = aspace.read_attribute_value(node, attr).Value.Value or 0
        if not level & bit:
            await aspace.write_attribute_value(node, attr, ua.DataValue(ua.Variant(level | bit, ua.VariantType.Byte)))
    historizing = aspace.read_attribute_value(node, _A.Historizing).Value
    if historizing is None or historizing.Value is not True:
        await aspace.write_attribute_value(node, _A.Historizing, ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))


# Encoded fields (name, VariantType, value) that repeat from event to event (a source, a state's id, a
# user), bounded; times, EventIds and arrays are encoded each time. Used by the history writer threads
# of the process (one a server): each use is one dictionary operation, atomic under the interpreter
# lock, and a miss only encodes the field again.
_REPEATING: dict[tuple[str, Any, Any], bytes] = {}
_REPEATING_MAX = 4096
_VARYING = frozenset({ua.VariantType.DateTime, ua.VariantType.ByteString})
# Never kept: 0.0 and -0.0 are one key but two encodings (and a NaN is never found again).
_UNKEPT = frozenset({ua.VariantType.Float, ua.VariantType.Double})
_VALUES: dict[tuple[Any, Any], bytes] = {}  # kept values' encodings, as _REPEATING (by VariantType, value)


Plan = tuple[tuple[str, Any], ...]  # the (name, VariantType) of an event's fields, in order


def event_plan(types: dict[str, Any], skip: Any = ()) -> Plan:
    """The fields an event of these ``types`` (asyncua's ``data_types``) is kept with: all but the
    private ones and those in ``skip`` (its ``internal_properties``)."""
    return tuple((name, vtype) for name, vtype in types.items() if not name.startswith("__") and name not in skip)


def encode_fields(values: dict[str, Any], plan: Plan) -> bytes:
    """An event's fields that have a value (its attributes ``values``, the fields of its ``plan``;
    asyncua's own helper fails on a None), each its name and its Variant (``decode_fields`` reads
    them). Run by the history writer thread, off the event loop; the plan is made once an event
    object (``HistoryService``)."""
    out = bytearray()
    for name, vtype in plan:
        value = values.get(name)
        if value is not None:
            out += _encoded(name, vtype, value)
    return bytes(out)


def encode_value(variant: ua.Variant) -> bytes:
    """A kept value's Variant, encoded (asyncua's bytes); a scalar that repeats (a state's name, an
    Id, a flag) is taken from a bounded cache by its VariantType and value."""
    vtype = variant.VariantType
    if variant.is_array or vtype in _VARYING or vtype in _UNKEPT:
        return bytes(variant_to_binary(variant))
    try:
        return _kept(_VALUES, (vtype, _hashable(variant.Value)), lambda: bytes(variant_to_binary(variant)))
    except TypeError:  # a value that cannot be a key (a structure)
        return bytes(variant_to_binary(variant))


def _encoded(name: str, vtype: Any, value: Any) -> bytes:
    if isinstance(value, list) or vtype in _UNKEPT:
        return _field(name, vtype, value)
    if vtype in _VARYING:
        return _varying(name, vtype, value)
    try:
        return _kept(_REPEATING, (name, vtype, _hashable(value)), lambda: _field(name, vtype, value))
    except TypeError:  # a value that cannot be a key (an unhashable structure)
        return _field(name, vtype, value)


def _hashable(value: Any) -> Any:
    """A key for ``value`` where asyncua's type is not hashable but repeats in every event (a state's
    name, a Message, a StatusCode): what its encoding depends on. The field's VariantType is in the
    key beside it, so a tuple made here never meets a value of another type."""
    if isinstance(value, ua.LocalizedText):
        return (value.Locale, value.Text)
    if isinstance(value, ua.StatusCode):
        return value.value
    if isinstance(value, ua.TimeZoneDataType):  # LocalTime: the same in every event
        return (ua.TimeZoneDataType, value.Offset, value.DaylightSavingInOffset)
    return value


def _kept(cache: dict[Any, bytes], key: Any, make: Callable[[], bytes]) -> bytes:
    """``cache[key]``, made by ``make`` the first time; the cache is emptied when it is full."""
    found = cache.get(key)
    if found is None:
        if len(cache) >= _REPEATING_MAX:
            cache.clear()
        found = cache[key] = make()
    return found


_NAMES: dict[str, bytes] = {}  # a field's name, encoded (as _REPEATING: shared, bounded, atomic uses)
_DATETIME = struct.Struct("<Bq")  # the Variant's encoding byte, the time
_BYTESTRING = struct.Struct("<Bi")  # the Variant's encoding byte, the length


def _varying(name: str, vtype: Any, value: Any) -> bytes:
    """A DateTime or ByteString field (new in every event: times, EventIds), written out: the bytes
    ``_field`` makes."""
    prefix = _kept(_NAMES, name, lambda: Primitives.String.pack(name))
    if isinstance(value, ua.Variant) and value.VariantType is vtype:  # an emitter's EventId: the same bytes
        value = value.Value
    if vtype is ua.VariantType.DateTime and isinstance(value, datetime):
        return prefix + _DATETIME.pack(vtype.value, ua.datetime_to_win_epoch(value))
    if vtype is ua.VariantType.ByteString and isinstance(value, bytes):
        return prefix + _BYTESTRING.pack(vtype.value, len(value)) + value
    return _field(name, vtype, value)


def _field(name: str, vtype: Any, value: Any) -> bytes:
    variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
    encoded: bytes = Primitives.String.pack(name) + variant_to_binary(variant)
    return encoded


def decode_fields(data: bytes) -> dict[str, ua.Variant]:
    buf = Buffer(data)
    fields: dict[str, ua.Variant] = {}
    while len(buf) > 0:
        name = Primitives.String.unpack(buf)
        fields[name] = variant_from_binary(buf)
    return fields


class _Once:
    """``encode()`` run once, in the writer thread, for every row that shares it (one thread calls it)."""

    __slots__ = ("_data", "_encode")

    def __init__(self, encode: Callable[[], bytes]) -> None:
        self._encode: Callable[[], bytes] | None = encode
        self._data = b""

    def __call__(self) -> bytes:
        if self._encode is not None:
            self._data, self._encode = self._encode(), None
        return self._data


class HistoryService:
    """Installed as ``iserver.history_manager``: asyncua's sessions hand it every HistoryRead."""

    def __init__(
        self,
        iserver: InternalServer,
        store: HistoryStore,
        allows: Callable[[str], bool],
        max_per_request: int = 10_000,
        max_events_per_request: int = 1_000,
    ) -> None:
        self.iserver = iserver
        self.allows = allows  # may a caller of this role HistoryRead (uacell.core.roles: "history_read")
        self.store = store
        self.max_per_request = max_per_request
        self.max_events_per_request = max_events_per_request
        self.slice = Slices().budget  # seconds of a request's work between two turns of the event loop
        # continuation points a session released (OPC 10000-4 7.9), by session; dropped when it closes
        self._released: dict[str, set[bytes]] = {}
        self._store_failing = False  # the last read failed in the store (logged once)
        self.values: dict[ua.NodeId, str] = {}
        self.notifiers: dict[ua.NodeId, str] = {}
        self._handles: list[int] = []
        self.where = WhereClause(getattr(iserver, "aspace", None))  # the WhereClause of ReadEventDetails
        self._tap: EventTap | None = None
        self._last_event: tuple[Any, int, str, _Once] | None = None  # EventId, time, type, its encoding
        self._plans: dict[int, tuple[Any, int, Plan]] = {}  # id(event object) -> (it, its type count, plan)

    # -- what is kept -----------------------------------------------------------------------------

    async def install(self, tap: EventTap) -> None:
        door.swap(self.iserver, "InternalServer.history_manager", self)
        self._tap = tap
        tap.listeners.append(self._on_event)
        self.store.start()

    def _on_event(self, event: Any) -> None:
        key = self.notifiers.get(getattr(event, "emitting_node", None))
        if key is not None:
            self._record_event(key, event)

    async def historize_value(self, node: ua.NodeId) -> None:
        """Keep every value ``node`` takes from now on; set Historizing and AccessLevel's HistoryRead."""
        if node in self.values:
            return
        aspace = self.iserver.aspace
        key = node_key(node)
        self.values[node] = key

        async def changed(_handle: int, dv: ua.DataValue) -> None:
            self._record_value(key, dv)

        status, handle = aspace.add_datachange_callback(node, _A.Value, changed)
        if not status.is_good():
            del self.values[node]
            raise HistoryError(status.value)
        self._handles.append(handle)
        await mark_historizing(aspace, node)
        # the value it has now is the first one kept
        self._record_value(key, aspace.read_attribute_value(node, _A.Value))

    async def historize_events(self, notifier: ua.NodeId) -> None:
        """Keep every event fired through ``notifier``; set EventNotifier's HistoryRead bit."""
        if notifier in self.notifiers:
            return
        self.notifiers[notifier] = node_key(notifier)
        aspace = self.iserver.aspace
        dv = aspace.read_attribute_value(notifier, _A.EventNotifier)
        level = (dv.Value.Value if dv.Value is not None else 0) or 0
        bits = ua.EventNotifier.SubscribeToEvents.mask | ua.EventNotifier.HistoryRead.mask
        await aspace.write_attribute_value(
            notifier, _A.EventNotifier, ua.DataValue(ua.Variant(level | bits, ua.VariantType.Byte))
        )

    def _record_value(self, key: str, dv: ua.DataValue) -> None:
        t = dv.SourceTimestamp or dv.ServerTimestamp or datetime.now(UTC)
        status = dv.StatusCode.value if dv.StatusCode is not None else 0
        variant = dv.Value if dv.Value is not None else ua.Variant()
        self.store.record(key, to_micros(t), VALUE, status, "", functools.partial(encode_value, variant))

    def _record_event(self, key: str, event: Any) -> None:
        try:
            event_id = getattr(event, "EventId", None)
            last = self._last_event
            if last is not None and event_id is not None and last[0] == event_id:
                # The same firing through another notifier (its EventId is the firing's, OPC 10000-5
                # 6.4.2; only the emitting node differs, not a field): one encoding for both rows.
                _, t, etype_text, encode = last
            else:
                # The event object is filled anew for its next firing: its fields are copied here (two
                # dictionary copies); the writer thread makes and encodes their Variants, once.
                values = dict(vars(event))
                t = to_micros(getattr(event, "Time", None) or datetime.now(UTC))
                etype = getattr(event, "EventType", None)
                etype_text = etype.to_string() if etype else ""
                encode = _Once(functools.partial(encode_fields, values, self._event_plan(event)))
                self._last_event = (event_id, t, etype_text, encode)
            self.store.record(key, t, EVENT, 0, etype_text, encode)
        except Exception:
            log.exception("history: could not keep an event")

    def _event_plan(self, event: Any) -> Plan:
        """The fields ``event`` is kept with, made once for each event object (an emitter fills its
        object anew for every firing; its ``data_types`` stay), again if its types changed."""
        types = getattr(event, "data_types", {})
        kept = self._plans.get(id(event))
        if kept is None or kept[0] is not event or kept[1] != len(types):
            if len(self._plans) >= _REPEATING_MAX:
                self._plans.clear()
            kept = self._plans[id(event)] = (
                event,
                len(types),
                event_plan(dict(types), getattr(event, "internal_properties", ())),
            )
        return kept[2]

    # -- asyncua's HistoryManager interface --------------------------------------------------------

    async def init(self) -> None:
        return None

    def update_history(self, params: ua.HistoryUpdateParameters) -> list[ua.HistoryUpdateResult]:
        # History is what happened: nobody rewrites it (Part 11: not supported).
        return [
            ua.HistoryUpdateResult(StatusCode=ua.StatusCode(_SC.BadHistoryOperationUnsupported))
            for _ in params.HistoryUpdateDetails
        ]

    async def stop(self) -> None:
        for handle in self._handles:
            self.iserver.aspace.delete_datachange_callback(handle)
        self._handles.clear()
        await self.store.close()

    async def read_history(self, params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        caller = current_caller()
        try:
            allowed = self.allows(caller.role)
        except ValueError:  # not a role uacell knows
            allowed = False
        results = []
        session = caller.session_id
        for rv in params.NodesToRead:
            if not allowed:
                results.append(_fail(_SC.BadUserAccessDenied))
                continue
            try:
                results.append(await self._read_one(params, rv, session))
                self._store_failing = False
            except (HistoryError, FilterError) as e:
                results.append(_fail(e.code))
            except Exception as exc:  # the store does not answer (a database gone): this node's answer
                results.append(_fail(_SC.BadNoCommunication))
                if not self._store_failing and not self.store.down:  # the writer said so already
                    log.warning("history: a read failed, answered Bad_NoCommunication: %s", first_line(exc))
                self._store_failing = True
        return results

    async def _read_one(
        self, params: ua.HistoryReadParameters, rv: ua.HistoryReadValueId, session: str
    ) -> ua.HistoryReadResult:
        details = params.HistoryReadDetails
        node = rv.NodeId
        if node not in self.iserver.aspace:
            raise HistoryError(_SC.BadNodeIdUnknown)
        stamps = params.TimestampsToReturn
        if not enums.known(stamps, ua.TimestampsToReturn) or (
            stamps == ua.TimestampsToReturn.Neither and not isinstance(details, ua.ReadEventDetails)
        ):
            raise HistoryError(_SC.BadTimestampsToReturnInvalid)  # Neither for values; a number out of range
        if isinstance(details, ua.ReadRawModifiedDetails):
            key = self._value_key(node)
            if details.IsReadModified:
                raise HistoryError(_SC.BadHistoryOperationUnsupported)  # values are never modified
            if params.ReleaseContinuationPoints:
                return self._release(key, rv, session, ua.HistoryData())
            if rv.IndexRange:
                try:
                    numeric_range.parse(rv.IndexRange)
                except numeric_range.RangeError as refused:
                    raise HistoryError(refused.code) from None
            after = self._after(key, rv, session)
            items, cp = await self._page(key, details, after, session)
            slices = Slices(self.slice)
            values = []
            for item in items:
                value = _raw_value(item, params.TimestampsToReturn)
                values.append(numeric_range.cut(value, rv.IndexRange) if rv.IndexRange else value)
                await slices.tick()
            found = any(isinstance(item, Sample) for item in items) or bool(rv.ContinuationPoint)
            return _ok(ua.HistoryData(DataValues=values), cp, found)
        if isinstance(details, ua.ReadEventDetails):
            notifier = self.notifiers.get(node)
            if notifier is None:
                raise HistoryError(_SC.BadHistoryOperationUnsupported)
            key = notifier
            if params.ReleaseContinuationPoints:
                return self._release(key, rv, session, ua.HistoryEvent())
            flt = details.Filter or ua.EventFilter()
            check_filter(flt)
            events, cp = await self._events(key, details, self._after(key, rv, session), flt, session)
            return _ok(ua.HistoryEvent(Events=events), cp, bool(events) or bool(rv.ContinuationPoint))
        if isinstance(details, ua.ReadProcessedDetails):
            key = self._value_key(node)
            if params.ReleaseContinuationPoints:
                return self._release(key, rv, session, ua.HistoryData())
            return await self._processed(key, details)
        if isinstance(details, ua.ReadAtTimeDetails):
            key = self._value_key(node)
            if params.ReleaseContinuationPoints:
                return self._release(key, rv, session, ua.HistoryData())
            return await self._at_times(key, details, rv, params.TimestampsToReturn, session)
        raise HistoryError(_SC.BadHistoryOperationUnsupported)  # annotations

    # -- continuation points ---------------------------------------------------------------------

    def _release(self, key: str, rv: ua.HistoryReadValueId, session: str, empty: Any) -> ua.HistoryReadResult:
        """ReleaseContinuationPoints: the point is checked (its session's, this node's) and never
        accepted again (OPC 10000-4 7.9 / 5.10.3)."""
        if rv.ContinuationPoint:
            self._after(key, rv, session)  # Bad_ContinuationPointInvalid when it is not this session's
            released = self._released.setdefault(session, set())
            if len(released) >= _RELEASED_MAX:
                released.clear()  # a session releasing without end: the oldest ones are forgotten
            released.add(bytes(rv.ContinuationPoint))
        return ua.HistoryReadResult(StatusCode=ua.StatusCode(_SC.Good), HistoryData=empty)

    def forget_session(self, session: Any) -> None:
        """A closed session's points are invalid anyway (signed for it): its release list goes."""
        self._released.pop(caller_of(session).session_id, None)

    def _after(self, key: str, rv: ua.HistoryReadValueId, session: str) -> tuple[int, int] | None:
        if not rv.ContinuationPoint:
            return None
        if bytes(rv.ContinuationPoint) in self._released.get(session, ()):
            raise HistoryError(_SC.BadContinuationPointInvalid)
        try:
            return self.store.cursor.decode(key, rv.ContinuationPoint, session)
        except ContinuationPointInvalid:
            raise HistoryError(_SC.BadContinuationPointInvalid) from None

    def _value_key(self, node: ua.NodeId) -> str:
        key = self.values.get(node)
        if key is None:
            raise HistoryError(_SC.BadHistoryOperationUnsupported)
        return key

    @staticmethod
    def _window(start: datetime | None, end: datetime | None, count: int) -> raw.Window:
        """The read's window by Part 11's StartTime/EndTime/NumValuesPerNode rules (``uacell.history.raw``)."""
        a = None if start is None or _unspecified(start) else to_micros(start)
        b = None if end is None or _unspecified(end) else to_micros(end)
        if a is None and b is None:
            raise HistoryError(_SC.BadInvalidTimestampArgument)
        if a is None and count <= 0:
            raise HistoryError(_SC.BadHistoryOperationInvalid)  # EndTime alone needs NumValuesPerNode
        return raw.Window.of(a, b)

    async def _page(
        self, key: str, details: ua.ReadRawModifiedDetails, after: tuple[int, int] | None, session: str
    ) -> tuple[list[raw.Item], bytes | None]:
        """One page of values, with the bounding values when ReturnBounds asks (``uacell.history.raw``)."""
        count = details.NumValuesPerNode
        window = self._window(details.StartTime, details.EndTime, count)
        limit = min(count, self.max_per_request) if count > 0 else self.max_per_request
        items, resume = await raw.page(self.store.read, key, window, limit, after, bool(details.ReturnBounds))
        if resume is None:
            return items, None
        return items, self.store.cursor.encode(key, *resume, session)

    async def _events(
        self, key: str, details: ua.ReadEventDetails, after: tuple[int, int] | None, flt: ua.EventFilter, session: str
    ) -> tuple[list[ua.HistoryEventFieldList], bytes | None]:
        """One page of events: at most ``max_events_per_request`` (and NumValuesPerNode); the stored
        rows are read in chunks by a worker thread and decoded, filtered and selected on the loop in
        slices (``Slices``), so that other clients are served meanwhile."""
        count = details.NumValuesPerNode
        window = self._window(details.StartTime, details.EndTime, count)
        if window.begin == window.end:  # OPC 10000-11, Good_NoData: "ReadEventDetails where startTime = endTime"
            return [], None
        cap = self.max_events_per_request
        limit = min(count, cap) if count > 0 else cap
        chunk = min(limit, _EVENT_CHUNK)
        names = [_selected(op) for op in flt.SelectClauses or []]
        out: list[ua.HistoryEventFieldList] = []
        slices = Slices(self.slice)
        while True:
            rows = await self.store.read(window.values(key, chunk, after, EVENT))
            for row in rows:
                fields = decode_fields(row.data)
                if self.where.matches(flt.WhereClause, functools.partial(_field_value, fields), _event_type(row.etype)):
                    out.append(ua.HistoryEventFieldList(EventFields=[_field_of(fields, n) for n in names]))
                    if len(out) == limit:
                        return out, self.store.cursor.encode(key, row.time, row.seq, session)
                await slices.tick()
            if len(rows) < chunk:
                return out, None
            after = (rows[-1].time, rows[-1].seq)

    async def _at_times(
        self,
        key: str,
        details: ua.ReadAtTimeDetails,
        rv: ua.HistoryReadValueId,
        which: ua.TimestampsToReturn,
        session: str,
    ) -> ua.HistoryReadResult:
        """ReadAtTimeDetails: a value for each of ReqTimes, in their order (``uacell.history.at_time``),
        at most ``max_per_request`` a page; a continuation point names the next instant's index."""
        times = details.ReqTimes or []
        if any(_unspecified(t) for t in times):
            raise HistoryError(_SC.BadInvalidTimestampArgument)
        first = 0
        if rv.ContinuationPoint:
            first, mark = self._after(key, rv, session) or (0, _AT_TIME)
            if mark != _AT_TIME:  # a raw read's point
                raise HistoryError(_SC.BadContinuationPointInvalid)
        if rv.IndexRange:
            try:
                numeric_range.parse(rv.IndexRange)
            except numeric_range.RangeError as refused:
                raise HistoryError(refused.code) from None
        now = to_micros(datetime.now(UTC))
        last = min(len(times), first + self.max_per_request)
        slices = Slices(self.slice)
        values = []
        for t in times[first:last]:
            us = to_micros(t)
            found = await at_time.read_at(self.store.read, key, us, bool(details.UseSimpleBounds), now)
            value = _datavalue(found.sample, found.status, us, which)
            values.append(numeric_range.cut(value, rv.IndexRange) if rv.IndexRange else value)
            await slices.tick()
        cp = self.store.cursor.encode(key, last, _AT_TIME, session) if last < len(times) else None
        return _ok(ua.HistoryData(DataValues=values), cp, bool(values) or bool(rv.ContinuationPoint))

    # -- processed values ------------------------------------------------------------------------

    async def _processed(self, key: str, details: ua.ReadProcessedDetails) -> ua.HistoryReadResult:
        if _unspecified(details.StartTime) or _unspecified(details.EndTime):
            raise HistoryError(_SC.BadInvalidTimestampArgument)
        start, end = to_micros(details.StartTime), to_micros(details.EndTime)
        if start > end:
            raise HistoryError(_SC.BadHistoryOperationUnsupported)  # reverse processed reads: not kept
        funcs = list(details.AggregateType or [])
        if len(funcs) != 1:
            raise HistoryError(_SC.BadAggregateListMismatch)
        name = AGGREGATES.get(funcs[0].Identifier) if funcs[0].NamespaceIndex == 0 else None
        if name is None:
            raise HistoryError(_SC.BadAggregateNotSupported)
        interval = int(details.ProcessingInterval * 1000) or (end - start)
        if math.ceil((end - start) / max(interval, 1)) > self.max_per_request:
            raise HistoryError(_SC.BadTooManyOperations)
        if name == "Interpolative":
            return await self._interpolative(key, start, end, interval)
        # the value before the start (for TimeAverage's first interval) and every one inside, decoded
        # in the reading thread (pure), then aggregated in a worker thread (pure): nothing of it on the loop
        before = await self.store.read_mapped(Query(key, VALUE, None, start, True, 1), _points)
        points: list[tuple[int, float | None, int]] = list(before)
        after: tuple[int, int] | None = None
        while True:
            rows = await self.store.read(Query(key, VALUE, start, end, False, _VALUE_CHUNK, after))
            points += await asyncio.to_thread(_points, rows)
            if len(rows) < _VALUE_CHUNK:
                break
            after = (rows[-1].time, rows[-1].seq)
        intervals = await asyncio.to_thread(aggregate, name, points, start, end, interval)
        slices = Slices(self.slice)
        dvs = []
        for iv in intervals:
            dvs.append(_processed_value(iv))
            await slices.tick()
        return ua.HistoryReadResult(HistoryData=ua.HistoryData(DataValues=dvs))

    async def _interpolative(self, key: str, start: int, end: int, interval: int) -> ua.HistoryReadResult:
        """OPC 10000-13 5.4.3.4: the Interpolated Bounding Value at each interval's start, its
        timestamp; Raw when a value was kept at that very time (``uacell.history.at_time``)."""
        now = to_micros(datetime.now(UTC))
        slices = Slices(self.slice)
        dvs = []
        for a, _b in intervals(start, end, max(1, interval)):
            found = await at_time.read_at(self.store.read, key, a, False, now)
            dvs.append(_datavalue(found.sample, found.status, a, ua.TimestampsToReturn.Both))
            await slices.tick()
        return ua.HistoryReadResult(HistoryData=ua.HistoryData(DataValues=dvs))

    async def close(self) -> None:
        if self._tap is not None and self._on_event in self._tap.listeners:
            self._tap.listeners.remove(self._on_event)


_RELEASED_MAX = 4096  # released continuation points remembered per session
_EVENT_CHUNK = 256  # stored events read at once (then decoded, filtered and selected in slices)
_VALUE_CHUNK = 50_000  # raw values read at once for an aggregate


def _selected(op: ua.SimpleAttributeOperand) -> str:
    """The stored field a select clause names (asyncua's ``Event.to_event_fields``: the browse path
    joined with "/", or the attribute's name without one)."""
    if not op.BrowsePath:
        return str(ua.AttributeIds(op.AttributeId).name)
    return "/".join(q.Name for q in op.BrowsePath)


def _field_of(fields: dict[str, ua.Variant], name: str) -> ua.Variant:
    """A selected field: its stored Variant (decoded for this event alone), a null Variant when the
    event has none."""
    found = fields.get(name)
    return found if found is not None else ua.Variant()


def _points(samples: list[Sample]) -> list[tuple[int, float | None, int]]:
    return [_point(s) for s in samples]


def _point(s: Sample) -> tuple[int, float | None, int]:
    v = variant_from_binary(Buffer(s.data)).Value
    try:
        num = float(v) if v is not None and not isinstance(v, (str, bytes)) else None
    except (TypeError, ValueError):
        num = None
    return s.time, num, s.status


def _processed_value(iv: Interval) -> ua.DataValue:
    t = from_micros(iv.start)
    if iv.value is None:
        return ua.DataValue(StatusCode=ua.StatusCode(_SC.BadNoData), SourceTimestamp=t, ServerTimestamp=t)
    variant = ua.Variant(iv.value, ua.VariantType.UInt32 if iv.integer else ua.VariantType.Double)
    status = ua.StatusCode(iv.status)
    return ua.DataValue(variant, StatusCode=status, SourceTimestamp=t, ServerTimestamp=t)


def check_filter(flt: ua.EventFilter) -> None:
    if not flt.SelectClauses:
        raise HistoryError(_SC.BadEventFilterInvalid)


def _datavalue(sample: Sample | None, status: int, time: int, which: ua.TimestampsToReturn) -> ua.DataValue:
    """``sample``'s value (None: no value) with ``status``, stamped ``time`` as TimestampsToReturn asks."""
    t = from_micros(time)
    src = t if which in (ua.TimestampsToReturn.Source, ua.TimestampsToReturn.Both) else None
    srv = t if which in (ua.TimestampsToReturn.Server, ua.TimestampsToReturn.Both) else None
    value = variant_from_binary(Buffer(sample.data)) if sample is not None else None
    return ua.DataValue(value, StatusCode=ua.StatusCode(status), SourceTimestamp=src, ServerTimestamp=srv)


def _raw_value(item: raw.Item, which: ua.TimestampsToReturn) -> ua.DataValue:
    """An item of a raw read: a kept value as kept, or a bound with none (Bad_BoundNotFound)."""
    if isinstance(item, raw.Missing):
        return _datavalue(None, _SC.BadBoundNotFound, item.time, which)
    return _datavalue(item, item.status, item.time, which)


def _ok(data: Any, cp: bytes | None, found: bool) -> ua.HistoryReadResult:
    code = _SC.Good if found else _SC.GoodNoData
    return ua.HistoryReadResult(StatusCode=ua.StatusCode(code), ContinuationPoint=cp, HistoryData=data)


def _fail(code: int) -> ua.HistoryReadResult:
    return ua.HistoryReadResult(StatusCode=ua.StatusCode(code))


def _field_value(fields: dict[str, ua.Variant], name: str) -> Any:
    """A stored event's field by name, as the WhereClause compares it (None if the event has none)."""
    variant = fields.get(name)
    return variant.Value if variant is not None else None


@functools.lru_cache(maxsize=256)
def _event_type(text: str) -> ua.NodeId | None:
    """A stored event's type (kept as its NodeId string; the same few types repeat)."""
    return ua.NodeId.from_string(text) if text else None
