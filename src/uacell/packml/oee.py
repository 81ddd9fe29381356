"""OEE of one PackML unit (pure): Availability, Performance, Quality and OEE over a window.

The unit's model hands every span of time it accounts (from one transition or tick to the next: the
mode and TR88 state it was in) and every production report; nothing is sampled. The definitions are
in docs/packml.md ("OEE"):

- **planned time**: time in Produce mode, except the line's loss (Suspending, Suspended,
  Unsuspending: the unit was starved or blocked by its neighbours, TR88's external stops);
- **Execute time**: time in Produce mode in Execute;
- **downtime** (planned time that is not Execute): Stopped, Stopping, Aborting, Aborted, Clearing,
  Holding, Held, Unholding (internal stops); setup: Resetting, Idle, Starting, Completing, Complete;
- Availability = Execute time / planned time;
- Performance = processed count / (MachDesignSpeed [per minute] x Execute time [minutes]);
- Quality = (processed - defective) / processed;
- OEE = Availability x Performance x Quality. A figure whose denominator is 0 is 0.

The window is the last ``window_hours`` or, with a shift calendar, since the start of the current
shift (times of day, UTC).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime, time, timedelta

PRODUCE_MODE = 1
EXECUTE = "Execute"
LINE_LOSS = frozenset({"Suspending", "Suspended", "Unsuspending"})

# A span's category: what it counts for.
RUN, PLANNED, UNPLANNED = 2, 1, 0


@dataclass(frozen=True)
class Figures:
    availability: float
    performance: float
    quality: float
    oee: float
    planned: float  # seconds of planned time in the window
    execute: float  # seconds in Execute in the window
    processed: int
    good: int

    def values(self) -> dict[str, float | int]:
        return {
            "OEE/Availability": self.availability,
            "OEE/Performance": self.performance,
            "OEE/Quality": self.quality,
            "OEE/OEE": self.oee,
            "OEE/ProcessedCount": self.processed,
            "OEE/GoodCount": self.good,
        }


def category(mode: int, state: str) -> int:
    if mode != PRODUCE_MODE or state in LINE_LOSS:
        return UNPLANNED
    return RUN if state == EXECUTE else PLANNED


def parse_shifts(shifts: list[str] | tuple[str, ...]) -> tuple[time, ...]:
    """ "HH:MM" times of day (UTC) at which shifts start; ValueError names a bad one."""
    out = []
    for s in shifts:
        try:
            h, m = s.split(":")
            out.append(time(int(h), int(m)))
        except ValueError:
            raise ValueError(f"shift start {s!r} is not HH:MM") from None
    return tuple(sorted(out))


def shift_start(now: datetime, shifts: tuple[time, ...]) -> datetime:
    """The start of the shift ``now`` falls in (the latest shift start at or before ``now``)."""
    day = now.astimezone(UTC).date()
    candidates = [datetime.combine(day + timedelta(days=d), t, tzinfo=UTC) for d in (-1, 0) for t in shifts]
    return max(c for c in candidates if c <= now)


class OEE:
    """Spans of (start, end, category) and counts (time, processed, defective), kept for the window."""

    def __init__(self, design_speed: float, window_hours: float = 8.0, shifts: tuple[time, ...] = ()) -> None:
        self.design_speed = design_speed  # products per minute
        self.window = window_hours * 3600.0
        self.shifts = shifts
        self._spans: deque[list[float]] = deque()  # [start, end, category], merged when adjacent
        self._counts: deque[tuple[float, int, int]] = deque()  # the reports at or after the window's start
        self._processed = 0  # sums of the reports in _counts (figures() runs on every publish: O(1))
        self._defective = 0

    def span(self, start: float, end: float, mode: int, state: str) -> None:
        """The unit was in ``mode``/``state`` from ``start`` to ``end`` (seconds, the model's clock)."""
        if end <= start:
            return
        cat = category(mode, state)
        last = self._spans[-1] if self._spans else None
        if last is not None and last[2] == cat and abs(last[1] - start) < 1e-9:
            last[1] = end
        else:
            self._spans.append([start, end, float(cat)])

    def count(self, at: float, processed: int, defective: int) -> None:
        self._counts.append((at, processed, defective))
        self._processed += processed
        self._defective += defective

    def window_start(self, now: float, wall: datetime | None = None) -> float:
        if self.shifts and wall is not None:
            return now - (wall - shift_start(wall, self.shifts)).total_seconds()
        return now - self.window

    def figures(self, now: float, wall: datetime | None = None) -> Figures:
        lo = self.window_start(now, wall)  # only ever moves forward: what falls out of it is dropped
        while self._spans and self._spans[0][1] <= lo:
            self._spans.popleft()
        while self._counts and self._counts[0][0] < lo:
            _, p, d = self._counts.popleft()
            self._processed -= p
            self._defective -= d
        planned = execute = 0.0
        for start, end, cat in self._spans:
            a, b = max(start, lo), min(end, now)
            if b <= a:
                continue
            if cat >= PLANNED:
                planned += b - a
            if cat == RUN:
                execute += b - a
        processed, defective = self._processed, self._defective
        good = max(0, processed - defective)
        availability = execute / planned if planned > 0 else 0.0
        expected = self.design_speed * execute / 60.0
        performance = processed / expected if expected > 0 else 0.0
        quality = good / processed if processed > 0 else 0.0
        return Figures(
            availability, performance, quality, availability * performance * quality, planned, execute, processed, good
        )
