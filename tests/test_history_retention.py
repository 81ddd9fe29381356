"""Retention under load (issue 39, docs/history.md "Size and retention"): a small size cap, samples
written fast, HistoryReads and PubSub over a real mosquitto going on, for about 12 s: pruning holds
the live data near the cap, the newest samples stay readable, PubSub keeps publishing."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.ua.ua_binary import variant_to_binary
from conftest import fast_config, start_app
from helpers import call_path, wait_until
from mqtt_broker import Broker, needs_mosquitto, subscribed

from uacell.history.backends import EVENT, VALUE, SqliteBackend
from uacell.history.service import encode_fields, event_plan, to_micros

pytestmark = needs_mosquitto

CAP_MB = 2.0
RUN = 12.0  # seconds of load
RATE = 1_500  # synthetic samples a second (half values, half events), beside the cell's own
PRUNE_EVERY = 1.0
V = ua.VariantType
TYPES = {
    "EventId": V.ByteString, "EventType": V.NodeId, "SourceNode": V.NodeId, "SourceName": V.String,
    "Time": V.DateTime, "ReceiveTime": V.DateTime, "Message": V.LocalizedText, "Severity": V.UInt16,
    "ToState": V.LocalizedText, "ToState/Id": V.NodeId,
}  # fmt: skip


async def test_pruning_holds_a_small_cap_while_writes_reads_and_pubsub_go_on(tmp_path: Path, broker: Broker) -> None:
    config = fast_config(tmp_path / "data")
    config.history.max_mb = CAP_MB
    config.pubsub.enabled = True
    config.pubsub.broker = broker.url
    config.pubsub.publisher_id = "retention"
    config.pubsub.publishing_interval = 0.05
    app = await start_app(config)
    try:
        assert app.history is not None
        store = app.history.store
        # prune every second (60 s in service: the test's minute is compressed, not its rule)
        store.settings = dataclasses.replace(store.settings, prune_interval=PRUNE_EVERY)
        backend = store.backend
        assert isinstance(backend, SqliteBackend)
        cap = int(CAP_MB * 1024 * 1024)
        async with (
            Client(app.endpoint, timeout=30, watchdog_intervall=30.0) as client,
            subscribed(broker, "opcua/json/data/#") as sub,
        ):
            ns = await client.get_namespace_index("urn:uacell:cell")
            speed_node = ua.NodeId("Filler1.Status.MachSpeed", ns)
            server = ua.NodeId(ua.ObjectIds.Server)
            value_key = app.history.values[ua.NodeId("Filler1.Status.CurMachSpeed", ns)]
            event_key = app.history.notifiers[server]
            plan = event_plan(TYPES)
            source = ua.NodeId("Filler1.BaseStateMachine.MachineState", ns)
            stop = time.monotonic() + RUN
            written = 0
            sizes: list[tuple[float, int]] = []
            reads: list[tuple[float, list[float]]] = []
            published: list[float] = []
            speeds: list[float] = []

            async def write() -> None:
                nonlocal written
                while time.monotonic() < stop:
                    t = datetime.now(UTC)
                    for i in range(RATE // 20):
                        us = to_micros(t) + i
                        if i % 2:
                            v = variant_to_binary(ua.Variant(float(written), V.Double))
                            store.record(value_key, us, VALUE, 0, "", v)
                        else:
                            fields = {
                                "EventId": written.to_bytes(16, "big"), "EventType": ua.NodeId(2311),
                                "SourceNode": source, "SourceName": "MachineState", "Time": t, "ReceiveTime": t,
                                "Message": ua.LocalizedText(f"transition {written}"), "Severity": 500,
                                "ToState": ua.LocalizedText("Execute"), "ToState/Id": ua.NodeId("Execute", ns),
                            }  # fmt: skip
                            store.record(event_key, us, EVENT, 0, "i=2311", encode_fields(fields, plan))
                        written += 1
                    await asyncio.sleep(0.05)

            async def change_speed() -> None:  # the cell's own writes: history values and PubSub data
                k = 0
                while time.monotonic() < stop:
                    k += 1
                    speed = float(k % 100)
                    res = await call_path(client, "Filler1", "SetMachSpeed", ua.Variant(speed, V.Float))
                    assert res.StatusCode.is_good(), res.StatusCode
                    speeds.append(speed)
                    await asyncio.sleep(0.1)

            async def read() -> None:  # HistoryRead of the newest speeds, newest first
                while time.monotonic() < stop:
                    details = ua.ReadRawModifiedDetails(
                        IsReadModified=False,
                        StartTime=datetime.now(UTC) + timedelta(seconds=1),
                        EndTime=datetime.now(UTC) - timedelta(seconds=5),
                        NumValuesPerNode=20,
                        ReturnBounds=False,
                    )
                    params = ua.HistoryReadParameters(
                        HistoryReadDetails=details,
                        TimestampsToReturn=ua.TimestampsToReturn.Source,
                        ReleaseContinuationPoints=False,
                        NodesToRead=[ua.HistoryReadValueId(NodeId=speed_node)],
                    )
                    (res,) = await client.uaclient.history_read(params)
                    assert res.StatusCode.is_good(), res.StatusCode
                    reads.append((time.monotonic(), [dv.Value.Value for dv in res.HistoryData.DataValues]))
                    await asyncio.sleep(0.25)

            async def watch() -> None:
                seen = 0
                while time.monotonic() < stop:
                    sizes.append((time.monotonic(), await asyncio.to_thread(backend.size)))
                    if len(sub.messages) > seen:
                        published.append(time.monotonic())
                        seen = len(sub.messages)
                    await asyncio.sleep(0.25)

            started = time.monotonic()
            await asyncio.gather(write(), change_speed(), read(), watch())
            await store.flush()
            await wait_until(lambda: store.written >= written, timeout=30)

        rows = backend._one("SELECT COUNT(*) FROM samples")
        oldest = backend._one("SELECT MIN(time) FROM samples")
        assert isinstance(rows, int) and isinstance(oldest, int)
        # more was written than the cap holds: pruning deleted the oldest, kept the newest
        assert rows < written
        assert oldest > to_micros(datetime.now(UTC)) - int(RUN * 1e6)
        # the cap held: once reached, the live data never grew past it by more than what arrives
        # between two prunes (1,500 samples a second, about 0.4 MB a second here; 2 prunes' worth)
        filled = [s for t, s in sizes if t > started + RUN / 3]
        assert filled and max(filled) <= cap + 2 * 1024 * 1024, (max(filled), cap)
        assert max(filled) >= cap * 0.5, "the cap was never approached: the test did not load the store"
        # reads went on and found the newest speeds throughout
        late = [values for t, values in reads if t > started + RUN / 2]
        assert late and all(values for values in late)
        assert speeds[-1] in (await _newest_speeds(app, speed_node))
        # PubSub went on publishing data to the end
        assert published and published[-1] > started + RUN * 0.8, (published[-3:], started)
    finally:
        await app.stop()


async def _newest_speeds(app: Any, node: ua.NodeId) -> list[float]:
    async with Client(app.endpoint, timeout=30, watchdog_intervall=30.0) as client:
        details = ua.ReadRawModifiedDetails(
            IsReadModified=False,
            StartTime=datetime.now(UTC) + timedelta(seconds=1),
            EndTime=datetime.now(UTC) - timedelta(minutes=5),
            NumValuesPerNode=10,
            ReturnBounds=False,
        )
        params = ua.HistoryReadParameters(
            HistoryReadDetails=details,
            TimestampsToReturn=ua.TimestampsToReturn.Source,
            ReleaseContinuationPoints=False,
            NodesToRead=[ua.HistoryReadValueId(NodeId=node)],
        )
        (res,) = await client.uaclient.history_read(params)
        return [dv.Value.Value for dv in res.HistoryData.DataValues]
