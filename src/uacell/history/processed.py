"""Aggregates of OPC 10000-13 over raw values (pure): Average, Minimum, Maximum, Count, TimeAverage
(Interpolative, the value at each interval's start, is ``uacell.history.at_time``'s).

The input is the raw values of one variable, oldest first, as (time in microseconds, number or None,
StatusCode); the value just before the first interval may lead them (TimeAverage's start). uacell's
historized variables change in steps (a state, a count, a speed set by a method): their
HistoricalDataConfiguration says Stepped, so TimeAverage holds each value until the next one
(Part 13 5.4.3.4 with stepped interpolation). Only Good values count (TreatUncertainAsBad, 100 %
PercentDataGood: an interval with any non-Good value is Uncertain).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from asyncua import ua

# AggregateFunction_* NodeIds of namespace 0 -> the aggregate's name.
AGGREGATES: dict[object, str] = {
    ua.ObjectIds.AggregateFunction_Average: "Average",
    ua.ObjectIds.AggregateFunction_Minimum: "Minimum",
    ua.ObjectIds.AggregateFunction_Maximum: "Maximum",
    ua.ObjectIds.AggregateFunction_Count: "Count",
    ua.ObjectIds.AggregateFunction_TimeAverage: "TimeAverage",
    # the Interpolated Bounding Value at each interval's start: ``uacell.history.at_time``, not ``aggregate``
    ua.ObjectIds.AggregateFunction_Interpolative: "Interpolative",
}

Point = tuple[int, float | None, int]

_GOOD = ua.StatusCodes.Good
_UNCERTAIN = ua.StatusCodes.UncertainDataSubNormal
# A StatusCode's low 16 bits (OPC 10000-4 7.39, Table 181): InfoType DataValue (0x400) says the
# InfoBits are a historian's (OPC 10000-11 6.3.2 / OPC 10000-4 Table 183): HistorianBits Calculated
# (0x1), and Partial (0x4) for an interval shorter than the others (the last).
DATA_VALUE_INFO = 0x400
CALCULATED = DATA_VALUE_INFO | 0x1
PARTIAL = 0x4


@dataclass(frozen=True)
class Interval:
    start: int
    value: float | int | None  # None: Bad_NoData
    status: int
    integer: bool = False


def counts(status: int) -> bool:
    """Whether a raw value of this StatusCode counts: Good only (TreatUncertainAsBad, the HA Configuration)."""
    return status & 0xC0000000 == 0


def _good(p: Point) -> bool:
    return counts(p[2]) and p[1] is not None


def intervals(start: int, end: int, interval: int) -> Iterator[tuple[int, int]]:
    t = start
    while t < end:
        yield t, min(t + interval, end)
        t += interval


def aggregate(name: str, points: Sequence[Point], start: int, end: int, interval: int) -> list[Interval]:
    interval = max(1, interval)
    out: list[Interval] = []
    i = 0
    prior: Point | None = None  # the last point before the current interval
    for a, b in intervals(start, end, interval):
        while i < len(points) and points[i][0] < a:
            prior = points[i]
            i += 1
        j = i
        while j < len(points) and points[j][0] < b:
            j += 1
        inside = points[i:j]
        partial = PARTIAL if b - a < interval else 0
        out.append(_one(name, a, b, inside, prior, partial))
    return out


def _one(name: str, a: int, b: int, inside: Sequence[Point], prior: Point | None, partial: int) -> Interval:
    good = [p for p in inside if _good(p)]
    uncertain = len(good) != len(inside)
    status = (_UNCERTAIN if uncertain else _GOOD) | CALCULATED | partial
    if name == "Count":
        # the number of Good raw values: 0 (Good, Calculated) for an interval without any (OPC 10000-13, Count)
        return Interval(a, len(good), status, integer=True)
    if name == "TimeAverage":
        return _time_average(a, b, inside, prior, partial)
    if not good:
        return Interval(a, None, ua.StatusCodes.BadNoData)
    values = [float(p[1]) for p in good if p[1] is not None]
    if name == "Average":
        return Interval(a, sum(values) / len(values), status)
    if name == "Minimum":
        return Interval(a, min(values), status)
    if name == "Maximum":
        return Interval(a, max(values), status)
    raise ValueError(name)


def _time_average(a: int, b: int, inside: Sequence[Point], prior: Point | None, partial: int) -> Interval:
    """Stepped: each value holds until the next; the span before the first known value is not counted."""
    steps: list[Point] = ([prior] if prior is not None else []) + list(inside)
    total = 0.0
    covered = 0
    bad = False
    for k, p in enumerate(steps):
        t0 = max(p[0], a)
        t1 = steps[k + 1][0] if k + 1 < len(steps) else b
        t1 = min(t1, b)
        if t1 <= t0:
            continue
        if not _good(p):
            bad = True
            continue
        assert p[1] is not None
        total += float(p[1]) * (t1 - t0)
        covered += t1 - t0
    if covered == 0:
        return Interval(a, None, ua.StatusCodes.BadNoData)
    whole = covered == b - a and not bad
    status = (_GOOD if whole else _UNCERTAIN) | CALCULATED | partial
    return Interval(a, total / covered, status)
