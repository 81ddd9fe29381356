"""One page of a raw HistoryRead (ReadRawModifiedDetails), with its bounding values when asked.

OPC 10000-11 ("Bounding Values and time domain", 4.4 in v1.04, 4.6 in v1.05) and its Table 1 of
examples say what a read returns. In the terms used here a read has a *window*:

- it **begins** at StartTime, or at EndTime when only EndTime is given (read newest first);
- it runs toward EndTime when both are given (newest first when StartTime is after EndTime), or on
  without end when only one time is given (NumValuesPerNode then ends each page).

The values are those at the beginning and on toward the end, the end itself excluded; when StartTime
equals EndTime, the values at that instant. With ``returnBounds`` the page also has:

- a **begin bound** when no value lies exactly at the beginning: the nearest value behind it (before
  StartTime when reading forward, after it when reading newest first), or, when there is none, a
  tuple with no value, the beginning's timestamp and Bad_BoundNotFound;
- an **end bound** when an end is given: the first value at or beyond the end that the read did not
  already return, or that empty tuple at EndTime;
- with no end given, once the values run out, the empty tuple one second beyond the last value
  returned (the footnotes of Table 1: a time beyond the data, since no EndTime names one).

Bounds count toward NumValuesPerNode, and continuation points go on through them: a page that ends
after the begin bound continues with the values, one that ends after the last value with the end
bound. Each item is either a stored ``Sample`` or a ``Missing`` bound.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from uacell.history.backends import VALUE, Query, Sample

SECOND = 1_000_000  # microseconds
_SEQ_MAX = 2**63 - 1


@dataclass(frozen=True)
class Missing:
    """A bound with no value: Bad_BoundNotFound at ``time`` (microseconds since the epoch)."""

    time: int


Item = Sample | Missing
Reader = Callable[[Query], Awaitable[list[Sample]]]


@dataclass(frozen=True)
class Window:
    """Where a read begins (microseconds), where it ends (None: no end) and which way it goes."""

    begin: int
    end: int | None
    reverse: bool

    @classmethod
    def of(cls, start: int | None, end: int | None) -> Window:
        """The window of StartTime and EndTime (None: not given; at least one is)."""
        if start is None:
            if end is None:
                raise ValueError("StartTime or EndTime is needed")
            return cls(end, None, True)
        if end is None:
            return cls(start, None, False)
        return cls(start, end, start > end)

    def values(self, key: str, limit: int, after: tuple[int, int] | None, kind: int = VALUE) -> Query:
        """The query of the samples: from the beginning (included) toward the end (excluded)."""
        b, e = self.begin, self.end
        if not self.reverse:
            hi = None if e is None else (e if e > b else b + 1)  # StartTime == EndTime: that instant
            return Query(key, kind, b, hi, False, limit, after)
        return Query(key, kind, e, b + 1, True, limit, after, lo_inclusive=False)

    def behind_begin(self, key: str) -> Query:
        """The value nearest the beginning, at it or behind it (against the read's direction)."""
        if self.reverse:
            return Query(key, VALUE, self.begin, None, False, 1)
        return Query(key, VALUE, None, self.begin + 1, True, 1)

    def beyond_end(self, key: str, end: int) -> Query:
        """The first value at or beyond the end that the values left out."""
        if self.reverse:
            return Query(key, VALUE, None, end + 1, True, 1)
        return Query(key, VALUE, end, None, False, 1, lo_inclusive=end != self.begin)

    def resume_after_begin(self, bound: Item) -> tuple[int, int]:
        """Where a page ending with the begin bound continues: every value of the window lies after it."""
        if isinstance(bound, Sample):
            return bound.time, bound.seq
        return (self.begin, _SEQ_MAX) if self.reverse else (self.begin, -1)

    def past(self, time: int) -> int:
        """One second beyond ``time`` in the read's direction (where the data of an open read ran out)."""
        return time - SECOND if self.reverse else time + SECOND


async def page(
    read: Reader, key: str, window: Window, limit: int, after: tuple[int, int] | None, bounds: bool
) -> tuple[list[Item], tuple[int, int] | None]:
    """At most ``limit`` items from ``after`` on (None: the read's first page), and where the next
    page continues (None: the read is complete)."""
    items: list[Item] = []
    resume: list[tuple[int, int]] = []  # per item: where a page ending with it continues
    if bounds and after is None:
        nearest = await read(window.behind_begin(key))
        if not nearest or nearest[0].time != window.begin:  # a value at the beginning is a value of the read
            bound: Item = nearest[0] if nearest else Missing(window.begin)
            items.append(bound)
            resume.append(window.resume_after_begin(bound))
    rows = await read(window.values(key, limit + 1 - len(items), after))
    for row in rows:
        items.append(row)
        resume.append((row.time, row.seq))
    if len(items) > limit:
        return items[:limit], resume[limit - 1]
    if bounds:
        items.append(await _end_bound(read, key, window, items, after))
        if len(items) > limit:
            return items[:limit], resume[limit - 1]
    return items, None


async def _end_bound(read: Reader, key: str, window: Window, items: list[Item], after: tuple[int, int] | None) -> Item:
    if window.end is not None:
        beyond = await read(window.beyond_end(key, window.end))
        return beyond[0] if beyond else Missing(window.end)
    last = items[-1].time if items else after[0] if after is not None else window.begin
    return Missing(window.past(last))


__all__ = ["SECOND", "Item", "Missing", "Window", "page"]
