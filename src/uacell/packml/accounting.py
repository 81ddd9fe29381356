"""A PackML unit's Admin accounting, free of OPC UA: the time spent in each unit mode and state, the
production counts, the OEE feed, and the durable values clients read (decision 28).

``PackMLUnit`` calls ``account`` at every transition, count and tick with its current mode and state;
the accounting adds the time since the last call and rebuilds the Admin times (whole seconds, Int32
with roll-over, OPC 30050 §6.3.4) only when one of them passed a whole second.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import Any

from uacell.packml.data import STATE_COLUMNS, Admin, counted, i32
from uacell.packml.oee import OEE
from uacell.packml.types import alarm_from_json, alarm_to_json, count_from_json, count_to_json

# The stored Admin values as clients read them (decision 28): published only once they are durable.
DURABLE_KEYS = (
    "Admin/ProdProcessedCount",
    "Admin/ProdDefectiveCount",
    "Admin/ProdConsumedCount",
    "Admin/ModeCumulativeTime",
    "Admin/StateCumulativeTime",
    "Admin/AccTimeSinceReset",
    "Admin/StopReason",
    "Admin/AlarmHistory",
)
DURABLE_TIMES = frozenset({"Admin/ModeCumulativeTime", "Admin/StateCumulativeTime", "Admin/AccTimeSinceReset"})


class AdminAccounting:
    """The Admin times and counts of one unit; ``admin`` is the unit's ``Admin``, ``modes`` the
    number of rows (the highest supported unit mode + 1)."""

    def __init__(self, admin: Admin, modes: int, oee: OEE, clock: Callable[[], float]) -> None:
        self.admin = admin
        self.oee = oee
        self._clock = clock
        self.mode_cum = [0.0] * modes
        self.state_cum = [[0.0] * STATE_COLUMNS for _ in range(modes)]
        self.mode_cur = 0.0
        self.state_cur = 0.0
        self.acc = 0.0
        self._shown: tuple[int, ...] | None = None  # what the Admin times were last built from
        self.last = clock()  # when ``account`` last ran

    def account(self, mode: int, state_number: int, state: str) -> bool:
        """Add the time since the last call to ``mode`` and ``state`` (and the OEE spans); True when
        the Admin times changed (a whole second passed, or the mode or state changed)."""
        now = self._clock()
        dt = max(0.0, now - self.last)
        self.last = now
        self.oee.span(now - dt, now, mode, state)
        self.mode_cum[mode] += dt
        self.state_cum[mode][state_number] += dt
        self.mode_cur += dt
        self.state_cur += dt
        self.acc += dt
        # Only the current mode's and state's entries moved: rebuild the Admin times (whole seconds) only
        # when one of those changed a whole second, or the mode or state changed.
        shown = (
            mode, state_number, i32(self.mode_cur), i32(self.state_cur), i32(self.mode_cum[mode]),
            i32(self.state_cum[mode][state_number]), i32(self.acc),
        )  # fmt: skip
        if shown == self._shown:
            return False
        self._shown = shown
        a = self.admin
        a.mode_current_time = [0] * len(self.mode_cum)
        a.mode_current_time[mode] = i32(self.mode_cur)
        a.mode_cumulative_time = [i32(x) for x in self.mode_cum]
        a.state_current_time = [[0] * STATE_COLUMNS for _ in self.state_cum]
        a.state_current_time[mode][state_number] = i32(self.state_cur)
        a.state_cumulative_time = [[i32(x) for x in row] for row in self.state_cum]
        a.acc_time_since_reset = i32(self.acc)
        return True

    def next_change(self, mode: int, state_number: int) -> float:
        """When (on the unit's clock) one of the Admin times ``account`` shows next passes a whole
        second, the mode and state staying as they are."""
        moving = (self.mode_cur, self.state_cur, self.mode_cum[mode], self.state_cum[mode][state_number], self.acc)
        return self.last + min(math.floor(x) + 1 - x for x in moving)

    def new_mode(self) -> None:
        """The unit mode changed: the current mode's and state's times start again."""
        self.mode_cur = self.state_cur = 0.0

    def new_state(self) -> None:
        self.state_cur = 0.0

    def reset(self) -> None:
        """Times and Count fields to zero (AccCount is kept); the next ``account`` rebuilds the times."""
        self.mode_cum = [0.0] * len(self.mode_cum)
        self.state_cum = [[0.0] * STATE_COLUMNS for _ in self.state_cum]
        self.mode_cur = self.state_cur = self.acc = 0.0
        self._shown = None
        a = self.admin
        for counts in (a.prod_processed_count, a.prod_defective_count, a.prod_consumed_count):
            counts[:] = [dataclasses.replace(c, count=0) for c in counts]

    def acknowledge_alarms(self, now: datetime) -> None:
        """Clear: the active alarms end, acknowledged at ``now`` in AlarmHistory."""
        a = self.admin
        active = {(x.id, x.date_time) for x in a.alarm}
        a.alarm_history[:] = [
            dataclasses.replace(h, ack_date_time=now, trigger=False) if (h.id, h.date_time) in active else h
            for h in a.alarm_history
        ]
        a.alarm.clear()

    def produce(self, processed: int, defective: int, consumed: int | Mapping[int, int]) -> None:
        """Add to the production counts (the first processed and defective counts; consumed by
        material ID, or the first material's). ``ValueError`` for an unknown material."""
        a = self.admin
        if processed:
            a.prod_processed_count[0] = counted(a.prod_processed_count[0], processed)
        if defective:
            a.prod_defective_count[0] = counted(a.prod_defective_count[0], defective)
        amounts = consumed if isinstance(consumed, Mapping) else {a.prod_consumed_count[0].id: consumed}
        for material, amount in amounts.items():
            if not amount:
                continue
            for i, c in enumerate(a.prod_consumed_count):
                if c.id == material:
                    a.prod_consumed_count[i] = counted(c, amount)
                    break
            else:
                raise ValueError(f"no ProdConsumedCount with ID {material}")

    def durable(self) -> dict[str, Any]:
        """The durable Admin values as clients read them (whole seconds, counts), by DURABLE_KEYS."""
        a = self.admin
        return {
            "Admin/ProdProcessedCount": list(a.prod_processed_count),
            "Admin/ProdDefectiveCount": list(a.prod_defective_count),
            "Admin/ProdConsumedCount": list(a.prod_consumed_count),
            "Admin/ModeCumulativeTime": list(a.mode_cumulative_time),
            "Admin/StateCumulativeTime": [list(r) for r in a.state_cumulative_time],
            "Admin/AccTimeSinceReset": a.acc_time_since_reset,
            "Admin/StopReason": a.stop_reason,
            "Admin/AlarmHistory": list(a.alarm_history),
        }

    def times(self) -> dict[str, Any]:
        """The Admin times that are not stored (the current mode's and state's)."""
        a = self.admin
        return {
            "Admin/ModeCurrentTime": list(a.mode_current_time),
            "Admin/StateCurrentTime": [list(r) for r in a.state_current_time],
        }

    def to_json(self, unit: str, saved_at: str) -> dict[str, Any]:
        """What the ``AdminStore`` keeps (the times unrounded)."""
        a = self.admin
        return {
            "unit": unit,
            "saved_at": saved_at,
            "prod_processed_count": [count_to_json(c) for c in a.prod_processed_count],
            "prod_defective_count": [count_to_json(c) for c in a.prod_defective_count],
            "prod_consumed_count": [count_to_json(c) for c in a.prod_consumed_count],
            "mode_cumulative_time": list(self.mode_cum),
            "state_cumulative_time": [list(r) for r in self.state_cum],
            "acc_time_since_reset": self.acc,
            "stop_reason": alarm_to_json(a.stop_reason),
            "alarm_history": [alarm_to_json(x) for x in a.alarm_history],
        }

    def load(self, data: Mapping[str, Any]) -> None:
        """Take what ``to_json`` stored; KeyError, TypeError or ValueError for inconsistent data."""
        a = self.admin
        for key, counts in (
            ("prod_processed_count", a.prod_processed_count),
            ("prod_defective_count", a.prod_defective_count),
            ("prod_consumed_count", a.prod_consumed_count),
        ):
            stored = {c.id: c for c in map(count_from_json, data.get(key, []))}
            counts[:] = [
                dataclasses.replace(c, count=stored[c.id].count, acc_count=stored[c.id].acc_count)
                if c.id in stored
                else c
                for c in counts
            ]
        for i, x in enumerate(data.get("mode_cumulative_time", [])[: len(self.mode_cum)]):
            self.mode_cum[i] = float(x)
        for i, row in enumerate(data.get("state_cumulative_time", [])[: len(self.state_cum)]):
            for j, x in enumerate(row[:STATE_COLUMNS]):
                self.state_cum[i][j] = float(x)
        self.acc = float(data.get("acc_time_since_reset", 0.0))
        if data.get("stop_reason"):
            a.stop_reason = alarm_from_json(data["stop_reason"])
        history = [alarm_from_json(x) for x in data.get("alarm_history", [])]
        a.alarm_history = history[-a.alarm_history_extent :]
