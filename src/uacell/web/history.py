"""The HMI's history view: what each companion's web view reads of its parts (``WebView.history``: per
PackML unit a state timeline, trends of speed and counts and the OEE figures, ``uacell.packml.web_view``;
per robot the timeline of its program runs, ``uacell.robotics.web_view``), under the parts' layout
keys. Read with HistoryRead through the web user's own OPC UA session (so its role applies), from the
nodes the HMI's discovery found (docs/web.md), with the helpers of ``uacell.binding.web_history``.

The page asks for what it draws, and only for what is new: trends come as one aggregate
per pixel column (OPC UA ReadProcessed: TimeAverage of a speed, Maximum of a count over each column,
on a grid of ``hours * 3600 / width`` seconds anchored at the epoch, so that columns of successive
polls line up), and a poll with ``since`` (the ``end`` of the answer before) reads history from then
on only: the state changes since, the columns from the one ``since`` falls in. What one poll costs
the server is bounded by the time since the last poll, not by the history kept.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from asyncua import Client

from uacell.binding.web_discovery import Cell
from uacell.binding.web_history import Window

MAX_HOURS = 168.0
WIDTH = 600  # pixel columns of a trend when the page does not say
MAX_WIDTH = 2000


async def cell_history(
    client: Client,
    cell: Cell,
    hours: float,
    now: datetime | None = None,
    *,
    since: float | None = None,
    width: int = WIDTH,
) -> dict[str, Any]:
    """The view of the last ``hours``: whole, or (``since``: the ``end`` of the answer before, within
    the view) only what came after it, for the page to add to what it has (``since`` in the answer)."""
    end = now or datetime.now(UTC)
    start = end - timedelta(hours=hours)
    width = max(10, min(MAX_WIDTH, width))
    column_us = max(1_000_000, round(hours * 3600e6 / width))
    since_t = (
        datetime.fromtimestamp(since, UTC)
        if since is not None and start.timestamp() < since <= end.timestamp()
        else None
    )
    w = Window(start, end, since_t or start, column_us)
    # Each companion's parts (``WebView.history``), under the layout key they are listed by.
    parts = {
        key: [await read(client, cell, part["name"], w) for part in cell.layout.get(key, [])]
        for key, read in cell.histories.items()
    }
    first = start.timestamp()
    if since_t is None:  # the view starts where history does (a server kept for less than ``hours`` fills the width)
        found = [p for answers in parts.values() for p in answers]
        known = [seg["start"] for p in found for seg in p.get("timeline", ())]
        known += [points[0][0] for p in found for points in p.get("trends", {}).values() if points]
        first = max(start.timestamp(), min(known, default=start.timestamp()))
    return {
        "start": first,
        "end": end.timestamp(),
        "hours": hours,
        "since": since_t.timestamp() if since_t is not None else None,
        "column": column_us / 1_000_000,
        "width": width,
        "keys": list(parts),
        **parts,
    }
