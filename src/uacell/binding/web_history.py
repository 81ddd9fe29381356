"""What the companions' history views read of their parts (``WebView.history``: per PackML unit a state
timeline, trends of speed and counts and the OEE figures, ``uacell.packml.web_view``; per robot the
timeline of its program runs, ``uacell.robotics.web_view``): the helpers that read values and
aggregates with HistoryRead through the web user's own OPC UA session (so its role applies), from the
nodes the HMI's discovery found (docs/web.md). The HMI's history view (``uacell.web.history``) calls
the views; these helpers live below the companions so that their views can use them.

``timeline`` and ``program_runs`` are pure: they turn value changes into segments.

Trends come as one aggregate per pixel column (OPC UA ReadProcessed: TimeAverage of a speed, Maximum
of a count over each column, on a grid of ``Window.column_us`` anchored at the epoch, so that columns
of successive polls line up), read from ``Window.since`` on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from asyncua import Client, ua

Change = tuple[float, Any]  # (seconds since the epoch, value or None when the status was bad)
TIME_AVERAGE = ua.ObjectIds.AggregateFunction_TimeAverage
MAXIMUM = ua.ObjectIds.AggregateFunction_Maximum


@dataclass(frozen=True)
class Segment:
    label: str
    start: float
    end: float

    def json(self) -> dict[str, Any]:
        return {"label": self.label, "start": self.start, "end": self.end, "seconds": self.end - self.start}


def _value_at(changes: Sequence[Change], t: float) -> Any:
    value = None
    for when, v in changes:
        if when > t:
            break
        value = v
    return value


def timeline(machines: Sequence[Sequence[Change]], start: float, end: float) -> list[Segment]:
    """The innermost active state over time: ``machines`` outermost first, each a list of changes
    (a machine that is not active has None). Adjacent equal states merge."""
    times = sorted({start, *(t for m in machines for t, _ in m if start < t < end)})
    out: list[Segment] = []
    for k, t in enumerate(times):
        t_end = times[k + 1] if k + 1 < len(times) else end
        label = None
        for m in machines:
            v = _value_at(m, t)
            if v is not None:
                label = str(v)
        if label is None:
            continue
        if out and out[-1].label == label and out[-1].end == t:
            out[-1] = Segment(label, out[-1].start, t_end)
        else:
            out.append(Segment(label, t, t_end))
    return out


def program_runs(states: Sequence[Change], programs: Sequence[Change], start: float, end: float) -> list[Segment]:
    """The spans a task control was Executing, each labelled with the program loaded when it started."""
    runs = [s for s in timeline([states], start, end) if s.label == "Executing"]
    return [Segment(str(_value_at(programs, r.start) or "(no program)"), r.start, r.end) for r in runs]


def text_of(value: Any) -> Any:
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, list):  # PackMLCountDataType[]: the sum of the counts
        return sum(int(getattr(c, "Count", 0) or 0) for c in value)
    return value


def seconds(t: datetime) -> float:
    return (t if t.tzinfo else t.replace(tzinfo=UTC)).timestamp()


async def value_history(client: Client, node: ua.NodeId, start: datetime, end: datetime) -> list[Change]:
    """Every value of ``node`` from ``start`` to ``end``, led by the last one before ``start``."""
    out: list[Change] = []

    async def read(details: ua.ReadRawModifiedDetails, cp: bytes | None) -> ua.HistoryReadResult:
        params = ua.HistoryReadParameters()
        params.HistoryReadDetails = details
        params.TimestampsToReturn = ua.TimestampsToReturn.Source
        params.ReleaseContinuationPoints = False
        params.NodesToRead = [ua.HistoryReadValueId(NodeId=node, ContinuationPoint=cp)]
        (result,) = await client.uaclient.history_read(params)
        return result

    def raw(s: datetime | None, e: datetime | None, count: int) -> ua.ReadRawModifiedDetails:
        d = ua.ReadRawModifiedDetails()
        d.IsReadModified = False
        d.StartTime = s or ua.get_win_epoch()
        d.EndTime = e or ua.get_win_epoch()
        d.NumValuesPerNode = count
        d.ReturnBounds = False
        return d

    before = await read(raw(None, start, 1), None)
    values = list(before.HistoryData.DataValues or []) if before.StatusCode.is_good() else []
    cp: bytes | None = None
    while True:
        res = await read(raw(start, end, 0), cp)
        if not res.StatusCode.is_good():
            break
        values += res.HistoryData.DataValues or []
        cp = res.ContinuationPoint
        if not cp:
            break
    for dv in values:
        t = dv.SourceTimestamp or dv.ServerTimestamp
        if t is None:
            continue
        good = dv.StatusCode is None or dv.StatusCode.is_good()
        out.append((max(seconds(t), seconds(start)), text_of(dv.Value.Value) if good and dv.Value else None))
    return out


@dataclass(frozen=True)
class Window:
    """What one answer covers: the view from ``start`` to ``end``, read from ``since`` on (``start``
    for a full answer), trends in columns of ``column_us`` microseconds."""

    start: datetime
    end: datetime
    since: datetime
    column_us: int

    @property
    def first_column(self) -> datetime:
        """The start of the column ``since`` falls in: that column is computed again, whole."""
        micros = int(seconds(self.since) * 1_000_000)
        return datetime.fromtimestamp((micros // self.column_us) * self.column_us / 1_000_000, UTC)


async def columns(client: Client, node: ua.NodeId, aggregate: int, w: Window) -> list[list[float]]:
    """``aggregate`` of ``node`` per column from ``w.first_column`` to ``w.end``: [[column start, value]],
    columns without a value left out (the page holds the one before)."""
    details = ua.ReadProcessedDetails()
    details.StartTime = w.first_column
    details.EndTime = w.end
    details.ProcessingInterval = w.column_us / 1000.0
    details.AggregateType = [ua.NodeId(aggregate)]
    details.AggregateConfiguration = ua.AggregateConfiguration(UseServerCapabilitiesDefaults=True)
    params = ua.HistoryReadParameters()
    params.HistoryReadDetails = details
    params.TimestampsToReturn = ua.TimestampsToReturn.Source
    params.ReleaseContinuationPoints = False  # asyncua's default is True: an empty answer
    params.NodesToRead = [ua.HistoryReadValueId(NodeId=node)]
    (result,) = await client.uaclient.history_read(params)
    if not result.StatusCode.is_good() or result.HistoryData is None:
        return []
    out = []
    for dv in result.HistoryData.DataValues or []:
        value = dv.Value.Value if dv.Value is not None else None
        bad = dv.StatusCode is not None and dv.StatusCode.value & 0x80000000
        if bad or not isinstance(value, int | float) or isinstance(value, bool) or dv.SourceTimestamp is None:
            continue
        out.append([seconds(dv.SourceTimestamp), float(value)])
    return out
