"""Reading history by OPC 10000-11, on a real SQLite store, in pure code:

- raw pages with bounding values (``uacell.history.raw``) against the examples of Table 1 ("Bounding
  Values and time domain"): values stored at 5:00, 5:02, 5:03, 5:05 and 5:06; FIRST and LAST are the
  tuples with no value and Bad_BoundNotFound, at StartTime and EndTime, or, where the request gives no
  such time, one second beyond the last value returned (the table's footnotes);
- ReadAtTimeDetails' value at an instant (``uacell.history.at_time``) from 6.5.5 and OPC 10000-13
  3.1.8/3.1.9 with Stepped and TreatUncertainAsBad."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from asyncua import ua

from uacell.history.at_time import value_at
from uacell.history.backends import VALUE, Query, Sample, SqliteBackend
from uacell.history.raw import SECOND, Item, Missing, Window, page

BASE = datetime(2026, 3, 2, 5, 0, tzinfo=UTC)
KEY = "ns=2;s=Speed"
STORED = ("5:00", "5:02", "5:03", "5:05", "5:06")


def at(clock: str) -> int:
    """Microseconds since the epoch of ``clock`` (H:MM) on the test's day."""
    hours, minutes = (int(x) for x in clock.split(":"))
    t = BASE.replace(hour=hours, minute=minutes)
    return int((t - datetime(1970, 1, 1, tzinfo=UTC)) / timedelta(microseconds=1))


def name(item: Item) -> str:
    """The table's notation: a stored value by its time, a bound with no value as FIRST/LAST@time."""
    if isinstance(item, Missing):
        return f"NONE@{item.time}"
    return next(c for c in STORED if at(c) == item.time)


# (StartTime, EndTime, NumValuesPerNode, returnBounds, the values of the first answer, a continuation point)
# as OPC 10000-11 Table 1 lists them; "-" is a time not given. FIRST@x / LAST@x: no value, Bad_BoundNotFound,
# at time x ("+1s"/"-1s": one second after/before the value before it, the footnotes' rule).
TABLE = [
    ("5:00", "5:05", 0, True, "5:00 5:02 5:03 5:05", False),
    ("5:00", "5:05", 0, False, "5:00 5:02 5:03", False),
    ("5:01", "5:04", 0, True, "5:00 5:02 5:03 5:05", False),
    ("5:01", "5:04", 0, False, "5:02 5:03", False),
    ("5:05", "5:00", 0, True, "5:05 5:03 5:02 5:00", False),
    ("5:05", "5:00", 0, False, "5:05 5:03 5:02", False),
    ("5:04", "5:01", 0, True, "5:05 5:03 5:02 5:00", False),
    ("5:04", "5:01", 0, False, "5:03 5:02", False),
    ("4:59", "5:05", 0, True, "FIRST@4:59 5:00 5:02 5:03 5:05", False),
    ("4:59", "5:05", 0, False, "5:00 5:02 5:03", False),
    ("5:01", "5:07", 0, True, "5:00 5:02 5:03 5:05 5:06 LAST@5:07", False),
    ("5:01", "5:07", 0, False, "5:02 5:03 5:05 5:06", False),
    ("5:00", "5:05", 3, True, "5:00 5:02 5:03", True),
    ("5:00", "5:05", 3, False, "5:00 5:02 5:03", False),
    ("5:01", "5:04", 3, True, "5:00 5:02 5:03", True),
    ("5:01", "5:04", 3, False, "5:02 5:03", False),
    ("5:05", "5:00", 3, True, "5:05 5:03 5:02", True),
    ("5:05", "5:00", 3, False, "5:05 5:03 5:02", False),
    ("5:04", "5:01", 3, True, "5:05 5:03 5:02", True),
    ("5:04", "5:01", 3, False, "5:03 5:02", False),
    ("4:59", "5:05", 3, True, "FIRST@4:59 5:00 5:02", True),
    ("4:59", "5:05", 3, False, "5:00 5:02 5:03", False),
    ("5:01", "5:07", 3, True, "5:00 5:02 5:03", True),
    ("5:01", "5:07", 3, False, "5:02 5:03 5:05", True),
    ("5:00", "-", 3, True, "5:00 5:02 5:03", True),
    ("5:00", "-", 3, False, "5:00 5:02 5:03", True),
    ("5:00", "-", 6, True, "5:00 5:02 5:03 5:05 5:06 LAST@+1s", False),
    ("5:00", "-", 6, False, "5:00 5:02 5:03 5:05 5:06", False),
    ("5:07", "-", 6, True, "5:06 LAST@+1s", False),
    ("5:07", "-", 6, False, "", False),
    ("-", "5:06", 3, True, "5:06 5:05 5:03", True),
    ("-", "5:06", 3, False, "5:06 5:05 5:03", True),
    ("-", "5:06", 6, True, "5:06 5:05 5:03 5:02 5:00 FIRST@-1s", False),
    ("-", "5:06", 6, False, "5:06 5:05 5:03 5:02 5:00", False),
    ("-", "4:48", 6, True, "5:00 FIRST@-1s", False),
    ("-", "4:48", 6, False, "", False),
    ("4:48", "4:48", 0, True, "FIRST@4:48 5:00", False),
    ("4:48", "4:48", 0, False, "", False),
    ("4:48", "4:48", 1, True, "FIRST@4:48", True),
    ("4:48", "4:48", 1, False, "", False),
    ("4:48", "4:48", 2, True, "FIRST@4:48 5:00", False),
    ("5:00", "5:00", 0, True, "5:00 5:02", False),
    ("5:00", "5:00", 0, False, "5:00", False),
    ("5:00", "5:00", 1, True, "5:00", True),
    ("5:00", "5:00", 1, False, "5:00", False),
    ("5:01", "5:01", 0, True, "5:00 5:02", False),
    ("5:01", "5:01", 0, False, "", False),
    ("5:01", "5:01", 1, True, "5:00", True),
    ("5:01", "5:01", 1, False, "", False),
]


def expected(text: str) -> list[str]:
    """The table's entries as ``name`` spells them, with the footnotes' times resolved."""
    out: list[str] = []
    for entry in text.split():
        if "@" not in entry:
            out.append(entry)
            continue
        when = entry.split("@")[1]
        if when in ("+1s", "-1s"):
            before = at(out[-1]) if out else None
            assert before is not None, "a footnote time follows a value"
            out.append(f"NONE@{before + (SECOND if when == '+1s' else -SECOND)}")
        else:
            out.append(f"NONE@{at(when)}")
    return out


@pytest.fixture
def backend(tmp_path: Path) -> SqliteBackend:
    store = SqliteBackend(tmp_path / "history.sqlite")
    store.write([(KEY, at(c), i + 1, VALUE, 0, "", b"") for i, c in enumerate(STORED)])
    store.write([("ns=2;s=Other", at("5:01"), 10, VALUE, 0, "", b"")])  # another node's value in between
    return store


def window(start: str, end: str) -> Window:
    return Window.of(None if start == "-" else at(start), None if end == "-" else at(end))


@pytest.mark.parametrize(("start", "end", "count", "bounds", "first", "more"), TABLE)
async def test_first_answer_is_the_standards_example(
    backend: SqliteBackend, start: str, end: str, count: int, bounds: bool, first: str, more: bool
) -> None:
    async def read(q: Query) -> list[Sample]:
        return backend.read(q)

    limit = count or 1000
    items, resume = await page(read, KEY, window(start, end), limit, None, bounds)
    assert [name(i) for i in items] == expected(first)
    assert (resume is not None) == more


@pytest.mark.parametrize("bounds", [True, False])
@pytest.mark.parametrize(("start", "end"), [("4:59", "5:07"), ("5:01", "5:04"), ("5:04", "5:01"), ("-", "5:06")])
async def test_pages_of_one_continue_through_the_bounds(
    backend: SqliteBackend, start: str, end: str, bounds: bool
) -> None:
    """Read one item a page through continuation points: the same items as one page of all of them."""

    async def read(q: Query) -> list[Sample]:
        return backend.read(q)

    w = window(start, end)
    whole, resume = await page(read, KEY, w, 1000, None, bounds)
    assert resume is None
    paged: list[Item] = []
    after = None
    for _ in range(20):
        items, after = await page(read, KEY, w, 1, after, bounds)
        paged += items
        if after is None:
            break
    assert [name(i) for i in paged] == [name(i) for i in whole]
    assert len(whole) >= 2


def test_a_window_needs_a_time() -> None:
    with pytest.raises(ValueError):
        Window.of(None, None)


# -- ReadAtTimeDetails (uacell.history.at_time) -------------------------------------------------

GOOD, UNCERTAIN, BAD = 0, ua.StatusCodes.UncertainDataSubNormal, ua.StatusCodes.BadSensorFailure
RAW_BITS, INTERPOLATED_BITS = 0x400, 0x402  # InfoType DataValue, HistorianBits Raw / Interpolated (Part 4 7.39)
NOW = at("5:30")


def kept(*entries: tuple[str, int]) -> list[Sample]:
    """Samples at the given times with the given statuses, newest first (as the store hands them)."""
    out = [Sample(KEY, at(c), i + 1, VALUE, status, "", b"") for i, (c, status) in enumerate(entries)]
    return sorted(out, key=lambda s: (s.time, s.seq), reverse=True)


# (values kept, the instant, UseSimpleBounds, the value's time (None: no value), the StatusCode)
AT_TIME = [
    # a value kept at the instant: Raw, with its own status
    ([("5:00", GOOD), ("5:02", GOOD)], "5:02", True, "5:02", GOOD | RAW_BITS),
    ([("5:00", GOOD), ("5:02", GOOD)], "5:02", False, "5:02", GOOD | RAW_BITS),
    # between values: the one before holds (Stepped), Interpolated
    ([("5:00", GOOD), ("5:02", GOOD)], "5:01", True, "5:00", GOOD | INTERPOLATED_BITS),
    ([("5:00", GOOD), ("5:02", GOOD)], "5:01", False, "5:00", GOOD | INTERPOLATED_BITS),
    # before the first value: Bad_NoData
    ([("5:00", GOOD)], "4:59", True, None, ua.StatusCodes.BadNoData),
    ([("5:00", GOOD)], "4:59", False, None, ua.StatusCodes.BadNoData),
    # a Bad value before the instant: simple bounds stop at it, interpolated ones skip it (Uncertain)
    ([("5:00", GOOD), ("5:02", BAD)], "5:03", True, None, ua.StatusCodes.BadNoData),
    ([("5:00", GOOD), ("5:02", BAD)], "5:03", False, "5:00", UNCERTAIN | INTERPOLATED_BITS),
    # a Bad value at the instant alike; Uncertain counts as Bad (TreatUncertainAsBad)
    ([("5:00", GOOD), ("5:02", BAD)], "5:02", True, None, ua.StatusCodes.BadNoData),
    ([("5:00", GOOD), ("5:02", BAD)], "5:02", False, "5:00", UNCERTAIN | INTERPOLATED_BITS),
    ([("5:00", GOOD), ("5:02", UNCERTAIN)], "5:03", False, "5:00", UNCERTAIN | INTERPOLATED_BITS),
    ([("5:02", BAD)], "5:03", False, None, ua.StatusCodes.BadNoData),
    # after the server's present: the last value extrapolated, Uncertain
    ([("5:00", GOOD)], "5:31", True, "5:00", UNCERTAIN | INTERPOLATED_BITS),
    ([("5:00", GOOD)], "5:29", True, "5:00", GOOD | INTERPOLATED_BITS),
    # two values at one instant: the later one holds
    ([("5:00", GOOD), ("5:02", GOOD), ("5:02", GOOD)], "5:02", True, "5:02", GOOD | RAW_BITS),
]


@pytest.mark.parametrize(("entries", "instant", "simple", "whose", "status"), AT_TIME)
def test_value_at_an_instant(
    entries: list[tuple[str, int]], instant: str, simple: bool, whose: str | None, status: int
) -> None:
    samples = [s for s in kept(*entries) if s.time <= at(instant)]
    got = value_at(samples, at(instant), simple, NOW)
    assert got.status == status
    assert (got.sample.time if got.sample else None) == (at(whose) if whose else None)
    if whose and len([e for e in entries if e[0] == whose]) > 1:
        assert got.sample is not None and got.sample.seq == max(s.seq for s in samples if s.time == at(whose))
