"""The history view: its pure parts (the state timeline of nested machines, a robot's program runs), and
what a poll of an open page costs the server as the history grows (issue 39 point 7)."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.ua.ua_binary import variant_to_binary
from conftest import fast_config, start_app

from uacell.binding.web_history import Segment, program_runs, timeline
from uacell.core.companion import web_views
from uacell.history.backends import VALUE
from uacell.history.service import to_micros
from uacell.web.discovery import discover
from uacell.web.history import cell_history


def test_timeline_takes_the_innermost_active_machine() -> None:
    base = [(0.0, "Cleared")]
    machine = [(0.0, "Stopped"), (10.0, "Running"), (40.0, "Stopping"), (42.0, "Stopped")]
    execute = [(0.0, None), (10.0, "Resetting"), (12.0, "Idle"), (20.0, "Execute"), (40.0, None)]
    got = timeline([base, machine, execute], 5.0, 50.0)
    assert got == [
        Segment("Stopped", 5.0, 10.0),
        Segment("Resetting", 10.0, 12.0),
        Segment("Idle", 12.0, 20.0),
        Segment("Execute", 20.0, 40.0),
        Segment("Stopping", 40.0, 42.0),
        Segment("Stopped", 42.0, 50.0),
    ]
    assert got[3].json()["seconds"] == 20.0


def test_timeline_before_any_value_is_empty_and_equal_states_merge() -> None:
    assert timeline([[(10.0, "Idle"), (20.0, "Idle")]], 0.0, 30.0) == [Segment("Idle", 10.0, 30.0)]
    assert timeline([[]], 0.0, 30.0) == []


def test_program_runs_are_the_executing_spans_named_by_the_loaded_program() -> None:
    states = [(0.0, "Idle"), (5.0, "Ready"), (10.0, "Executing"), (25.0, "Ready"), (30.0, "Executing")]
    programs = [(0.0, ""), (4.0, "pick.robot"), (28.0, "place.robot")]
    assert program_runs(states, programs, 0.0, 40.0) == [
        Segment("pick.robot", 10.0, 25.0),
        Segment("place.robot", 30.0, 40.0),
    ]


# --- issue 39 point 7: what one poll of an open page costs does not grow with the history kept ------
WIDTH = 120


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory):
    app = await start_app(fast_config(tmp_path_factory.mktemp("webhistory") / "data"))
    try:
        async with Client(app.endpoint, timeout=60, watchdog_intervall=60) as client:
            yield app, client, await discover(client, web_views(app.companions))
    finally:
        await app.stop()


class Work:
    """What the server's HistoryRead answers: values encoded, counted per request."""

    def __init__(self, app, monkeypatch) -> None:
        self.values = 0
        original = app.history.read_history

        async def counted(params):
            results = await original(params)
            for r in results:
                data = r.HistoryData
                self.values += len(getattr(data, "DataValues", None) or getattr(data, "Events", None) or [])
            return results

        monkeypatch.setattr(app.history, "read_history", counted)

    def take(self) -> int:
        values, self.values = self.values, 0
        return values


async def _fill(app, cell, count: int, start: datetime, end: datetime) -> None:
    """``count`` MachSpeed values of Filler1 spread from ``start`` to ``end``, straight into the store."""
    key = app.history.values[cell.variables["Filler1/Status/MachSpeed"]]
    step = (end - start) / count
    for i in range(count):
        value = variant_to_binary(ua.Variant(100.0 + i % 50, ua.VariantType.Double))
        app.history.store.record(key, to_micros(start + step * i), VALUE, 0, "", value)
    await app.history.store.flush()


async def _poll(app, client, cell, answer: dict[str, Any], work: Work) -> tuple[dict[str, Any], int, int]:
    """The page's poll 15 s after ``answer``: what is new since its end. (answer, bytes, values read)."""
    now = datetime.fromtimestamp(answer["end"], UTC) + timedelta(seconds=15)
    await _fill(app, cell, 3, now - timedelta(seconds=14), now - timedelta(seconds=1))
    work.take()
    polled = await cell_history(client, cell, 1.0, now, since=answer["end"], width=WIDTH)
    return polled, len(json.dumps(polled)), work.take()


@pytest.mark.asyncio(loop_scope="module")
async def test_a_poll_of_the_history_view_costs_the_same_whatever_the_history_kept(served, monkeypatch):
    app, client, cell = served
    work = Work(app, monkeypatch)
    # On a column boundary (30 s at 120 columns an hour): each poll below then spans one column.
    now = datetime.fromtimestamp((int(datetime.now(UTC).timestamp()) // 30 + 10) * 30, UTC)
    hour_ago = now - timedelta(hours=1)
    await _fill(app, cell, 2_000, hour_ago, now - timedelta(minutes=1))
    full = await cell_history(client, cell, 1.0, now, width=WIDTH)
    full_bytes, full_values = len(json.dumps(full)), work.take()
    speed = full["units"][0]["trends"]["MachSpeed"]
    assert 0 < len(speed) <= WIDTH + 2  # one value per pixel column (and the value now), not 2,000 raw ones
    assert full["since"] is None and full["column"] == 30.0
    polled, poll_bytes, poll_values = await _poll(app, client, cell, full, work)
    assert polled["since"] == full["end"]
    assert 1 <= len(polled["units"][0]["trends"]["MachSpeed"]) <= 3  # the column of `since`, a new one, now

    # Ten times the history in the same hour: the answers stay the same size.
    await _fill(app, cell, 18_000, hour_ago + timedelta(seconds=1), now - timedelta(minutes=2))
    full10 = await cell_history(client, cell, 1.0, datetime.fromtimestamp(polled["end"], UTC), width=WIDTH)
    assert len(full10["units"][0]["trends"]["MachSpeed"]) <= WIDTH + 2
    assert len(json.dumps(full10)) < 1.3 * full_bytes
    assert work.take() < 1.3 * full_values
    _, poll10_bytes, poll10_values = await _poll(app, client, cell, full10, work)
    assert poll10_bytes < 1.3 * poll_bytes  # what the server encodes per poll: not 10 times more
    assert poll10_values <= poll_values + 2
    assert poll_bytes < full_bytes / 3  # and a poll is a fraction of the whole view
