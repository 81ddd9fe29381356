"""The value of a kept variable at an instant, for ReadAtTimeDetails (OPC 10000-11 6.5.5).

Where no value was kept at the instant itself, the standard has it interpolated as the Interpolative
aggregate does (OPC 10000-13 5.4.3.4), from simple bounding values (``UseSimpleBounds``, 3.1.9) or
interpolated ones (3.1.8). uacell's kept variables are Stepped (their HA Configuration says so), so a
value holds until the next one: the value at an instant is the one kept at it, or else the one before.
With TreatUncertainAsBad (also in the HA Configuration) only Good values count as non-Bad.

- Simple bounds: the last value kept at or before the instant; Bad_NoData if it is not Good or if
  there is none.
- Interpolated bounds: the last Good value at or before the instant, skipping the others; Uncertain_
  DataSubNormal when it skipped any, Bad_NoData when there is none within ``SEARCH`` values.
- A value kept at the instant is Raw; one taken from before it is Interpolated (the InfoBits of the
  StatusCode, InfoType DataValue). An instant after the server's present is Uncertain_DataSubNormal:
  uacell keeps every change of a kept variable as it happens, so up to now the value before an instant
  is what the variable held; beyond now it is an extrapolation (OPC 10000-13 3.1.9 lets a historian that
  knows how its data is collected extend its last value so).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from asyncua import ua

from uacell.history.backends import VALUE, Query, Sample
from uacell.history.processed import DATA_VALUE_INFO, counts

SEARCH = 1000  # kept values looked at, at and before an instant, for one that counts
RAW = DATA_VALUE_INFO  # HistorianBits Raw (0)
INTERPOLATED = DATA_VALUE_INFO | 0x2
_GOOD = ua.StatusCodes.Good
_UNCERTAIN = ua.StatusCodes.UncertainDataSubNormal
_NO_DATA = ua.StatusCodes.BadNoData

Reader = Callable[[Query], Awaitable[list[Sample]]]


@dataclass(frozen=True)
class AtTime:
    """What an instant reads: the kept sample whose value it is (None: no value) and the StatusCode."""

    sample: Sample | None
    status: int


def value_at(newest_first: list[Sample], t: int, simple: bool, now: int) -> AtTime:
    """The value at ``t`` from the values kept at or before it, newest first (pure)."""
    skipped = False
    for sample in newest_first:
        if not counts(sample.status):
            if simple:
                return AtTime(None, _NO_DATA)
            skipped = True
            continue
        if sample.time == t:
            return AtTime(sample, (sample.status & 0xFFFF0000) | RAW)
        uncertain = skipped or t > now
        return AtTime(sample, (_UNCERTAIN if uncertain else _GOOD) | INTERPOLATED)
    return AtTime(None, _NO_DATA)


async def read_at(read: Reader, key: str, t: int, simple: bool, now: int) -> AtTime:
    """The value at ``t`` of the variable kept under ``key``."""
    rows = await read(Query(key, VALUE, None, t + 1, True, 1 if simple else SEARCH))
    return value_at(rows, t, simple, now)


__all__ = ["INTERPOLATED", "RAW", "SEARCH", "AtTime", "read_at", "value_at"]
