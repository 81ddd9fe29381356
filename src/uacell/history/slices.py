"""Work on the event loop in short slices: a history request never holds the loop for long.

A HistoryRead decodes, filters and selects each stored sample on the event loop (the address space
and the filter's types live there); ``Slices.tick`` after each sample hands the loop back to every
other client once the slice has taken ``budget`` seconds. docs/history.md ("Other clients").
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

SLICE = 0.005  # seconds of history work between two turns of the event loop


class Slices:
    def __init__(self, budget: float = SLICE, clock: Callable[[], float] = time.perf_counter) -> None:
        self.budget = budget
        self.clock = clock
        self.started = clock()
        self.yields = 0  # how often the work gave the loop back

    async def tick(self) -> None:
        """Give the loop back when this slice is used up; the next slice starts after that turn."""
        if self.clock() - self.started >= self.budget:
            await asyncio.sleep(0)
            self.yields += 1
            self.started = self.clock()
