"""A call is answered before its changes are published, and no request is served before they are
(docs/decisions.md 56): the publisher and the pipeline's PublishedStage, then a real server and
clients over TCP."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import raw_call, wait_until

from uacell.binding.publisher import Publisher
from uacell.robotics.binding import CONTROLLERS
from uacell.ua.pipeline import PublishedStage

TC = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"


async def test_a_request_waits_for_what_is_being_published() -> None:
    publisher = Publisher()
    stage = PublishedStage(publisher)
    published: list[str] = []
    release, started = asyncio.Event(), asyncio.Event()

    async def held() -> None:
        started.set()
        await release.wait()
        published.append("held")

    async def quick() -> None:
        published.append("quick")

    seen: list[list[str]] = []

    async def service(request: Any) -> str:
        seen.append(list(published))
        return "answer"

    request: Any = None  # the stage looks at the publisher only
    assert not publisher.pending
    assert await stage(request, service) == "answer"  # nothing to wait for
    publisher.submit(held)
    publisher.submit(quick)
    assert publisher.pending  # a drain is due: the loop's next turn
    waiting = asyncio.ensure_future(stage(request, service))
    await started.wait()  # the drain holds; the request, started after it, is in the stage
    assert not waiting.done() and len(seen) == 1 and publisher.pending
    release.set()
    assert await waiting == "answer"
    assert seen[-1] == ["held", "quick"]  # served after everything submitted before it
    assert not publisher.pending


async def test_a_publishing_that_hangs_holds_up_a_request_only_so_long(caplog: pytest.LogCaptureFixture) -> None:
    publisher = Publisher()
    stage = PublishedStage(publisher, wait=0.2)
    release, started = asyncio.Event(), asyncio.Event()

    async def stuck() -> None:
        started.set()
        await release.wait()

    async def service(request: Any) -> str:
        return "answer"

    publisher.submit(stuck)
    await started.wait()
    request: Any = None
    with caplog.at_level(logging.WARNING, logger="uacell.ua.pipeline"):
        assert await asyncio.wait_for(stage(request, service), 10) == "answer"
    assert "publishing has waited more than 0.2 s" in caplog.text
    assert publisher.pending  # the drain goes on
    release.set()
    await publisher.flush()
    assert not publisher.pending


async def test_schedule_runs_the_idle_hooks_with_nothing_queued() -> None:
    publisher = Publisher()
    ran: list[int] = []

    async def hook() -> None:
        ran.append(1)

    publisher.idle_hooks.append(hook)
    publisher.schedule()
    publisher.schedule()  # one drain for both
    assert publisher.pending
    await publisher.flush()
    assert ran == [1] and not publisher.pending


async def test_a_call_is_answered_first_and_a_read_after_it_sees_what_it_changed(tmp_path: Path) -> None:
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        task = app.registry(CONTROLLERS)["Robot1.Controllers.Controller1"].cell.tasks["TaskControl1"]
        release = asyncio.Event()
        holding = False

        async def held() -> None:
            await release.wait()

        def hold_first(change: Any) -> None:  # ahead of the binding's own jobs for the same change
            nonlocal holding
            if not holding:
                holding = True
                app.publisher.submit(held)

        flushes: list[int] = []
        real_flush = app.publisher.flush

        async def counted_flush(timeout: float | None = None) -> None:
            flushes.append(1)
            await real_flush(timeout)

        app.publisher.flush = counted_flush  # type: ignore[method-assign]
        state = ua.NodeId(f"{TC}.CurrentState", ns)
        load = ua.NodeId(f"{TC}.LoadByName", ns)
        async with Client(app.endpoint, timeout=30) as other:  # connected first: its requests pass the stage too
            task.machine.listeners.insert(0, hold_first)
            try:
                # Answered while its changes wait in the publisher (before decision 56 it would not be).
                result = await asyncio.wait_for(
                    raw_call(client, ua.NodeId(TC, ns), load, ua.Variant("pick_and_place", ua.VariantType.String)), 10
                )
                assert result.StatusCode.is_good() and result.OutputArguments[0].Value == 0
                assert task.machine.current == "Ready"  # the model moved...
                server_side = app.server.get_node(state)
                assert (await server_side.read_value()).Text == "Idle"  # ...the address space not yet
                # Another client's Read waits in the PublishedStage until the changes are in.
                reading = asyncio.ensure_future(other.get_node(state).read_value())
                await wait_until(lambda: flushes != [])
                assert not reading.done()
                release.set()
                assert (await asyncio.wait_for(reading, 10)).Text == "Ready"
            finally:
                release.set()  # a failing test must not leave the publisher held: every request would wait
        assert (await client.get_node(state).read_value()).Text == "Ready"
        task.machine.listeners.remove(hold_first)
        unload = ua.NodeId(f"{TC}.UnloadProgram", ns)
        assert (await raw_call(client, ua.NodeId(TC, ns), unload)).OutputArguments[0].Value == 0
        assert (await client.get_node(state).read_value()).Text == "Idle"


async def test_a_0_ms_subscription_gets_what_one_call_changed_in_one_message(tmp_path: Path) -> None:
    """asyncua publishes a 0 ms subscription at the first change of each monitored item: the first of a
    call's changes went alone, the rest in a second message. uacell publishes once per event-loop
    turn (door/publishing.py): one NotificationMessage, after the answer."""
    names = ("CurrentState", "CurrentState.Id", "LastTransition", "LastTransition.Id")
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        seen: list[tuple[int, str]] = []  # (the message's sequence number, the variable)
        by_node = {ua.NodeId(f"{TC}.{name}", ns): name for name in names}

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                seen.append((subscription.last_sequence_number, by_node[node.nodeid]))

        subscription = await client.create_subscription(0, Handler())
        await subscription.subscribe_data_change([client.get_node(n) for n in by_node], sampling_interval=0)
        await wait_until(lambda: len(seen) == len(names))  # the initial values
        seen.clear()
        load = ua.NodeId(f"{TC}.LoadByName", ns)
        result = await raw_call(client, ua.NodeId(TC, ns), load, ua.Variant("pick_and_place", ua.VariantType.String))
        assert result.StatusCode.is_good() and result.OutputArguments[0].Value == 0
        await wait_until(lambda: len(seen) == len(names), timeout=10)
        assert sorted(name for _, name in seen) == sorted(names)
        assert len({seq for seq, _ in seen}) == 1, seen  # one message
        unload = ua.NodeId(f"{TC}.UnloadProgram", ns)
        assert (await raw_call(client, ua.NodeId(TC, ns), unload)).OutputArguments[0].Value == 0
        await wait_until(lambda: len(seen) == 2 * len(names), timeout=10)
        assert len({seq for seq, _ in seen[len(names) :]}) == 1, seen
        await subscription.delete()


async def test_a_deadband_compares_with_the_last_value_reported_and_a_status_change_passes(tmp_path: Path) -> None:
    """A client's absolute deadband (OPC 10000-4 7.22.2) compares each new value with the last one
    reported, and a change of the status is reported whatever the deadband. asyncua compared with the
    value before: the drift 100 -> 100.5 -> 101.2 was never reported, nor an Uncertain status on an
    unchanged value (door/monitoring.py, ua/datachange.py)."""
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        seen: list[tuple[float, int]] = []  # (the value, its StatusCode)

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                seen.append((round(val, 3), data.monitored_item.Value.StatusCode.value))

        speed = ua.NodeId("Filler1.Status.MachSpeed", ns)
        filler = client.get_node(ua.NodeId("Filler1", ns))
        set_speed = ua.NodeId("Filler1.SetMachSpeed", ns)
        await filler.call_method(set_speed, ua.Variant(100.0, ua.VariantType.Float))
        subscription = await client.create_subscription(0, Handler())
        await subscription.deadband_monitor(client.get_node(speed), 1.0)
        await wait_until(lambda: [v for v, _ in seen] == [100.0])  # the value it has
        for value in (100.5, 101.2, 101.9, 99.0):
            await filler.call_method(set_speed, ua.Variant(value, ua.VariantType.Float))
        await wait_until(lambda: len(seen) >= 3, timeout=10)
        # 100.5: within 1.0 of 100 (reported); 101.2: 1.2 from it; 101.9: 0.7 from 101.2; 99.0: 2.9
        assert [v for v, _ in seen] == [100.0, 101.2, 99.0]
        uncertain = ua.StatusCode(ua.StatusCodes.UncertainLastUsableValue)
        same = ua.DataValue(ua.Variant(99.0, ua.VariantType.Float), StatusCode=uncertain)
        await app.server.write_attribute_value(speed, same)  # the value unchanged, its quality not
        await wait_until(lambda: len(seen) == 4, timeout=10)
        assert seen[-1] == (99.0, uncertain.value)
        await subscription.delete()


class Values:
    """A subscription's handler that keeps the values it is sent."""

    def __init__(self) -> None:
        self.seen: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.seen.append(val)


async def test_a_0_ms_subscription_is_revised_and_kept_alive(tmp_path: Path) -> None:
    """OPC 10000-4 5.14.2.2: a requested publishing interval of 0 is revised to the fastest the server
    supports. asyncua kept 0 and ran no loop for it, so an idle subscription never got a keep-alive,
    and asyncua's own client took it for lost after a second and made it again (its values sent
    twice). Now it is revised to 50 ms and gets asyncua's keep-alives (decision 79)."""
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        values = Values()
        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=0,
            RequestedLifetimeCount=30,
            RequestedMaxKeepAliveCount=3,
            PublishingEnabled=True,
        )
        subscription = await client.create_subscription(params, values)
        first_id = subscription.subscription_id
        served = app.server.iserver.subscription_service.subscriptions[first_id]
        assert served.data.RevisedPublishingInterval == 50.0
        # asyncua's client sends back the revised interval with a keep-alive count of its own (large):
        # three again, by ModifySubscription, so that keep-alives come every 150 ms
        modify = ua.ModifySubscriptionParameters(
            SubscriptionId=first_id, RequestedPublishingInterval=50.0, RequestedLifetimeCount=30,
            RequestedMaxKeepAliveCount=3,
        )  # fmt: skip
        revised = await client.uaclient.update_subscription(modify)
        assert (revised.RevisedPublishingInterval, revised.RevisedLifetimeCount) == (50.0, 30)
        assert revised.RevisedMaxKeepAliveCount == served.data.RevisedMaxKeepAliveCount == 3
        await subscription.subscribe_data_change(client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns)))
        await wait_until(lambda: len(values.seen) == 1)
        idle_from = time.monotonic()
        # a keep-alive arrives after the second in which asyncua's client would have made it again
        await wait_until(lambda: (subscription.last_publish_at or 0.0) > idle_from + 1.5, timeout=10)
        assert subscription.subscription_id == first_id and len(values.seen) == 1  # not made again, nothing twice
        await subscription.delete()


async def test_a_subscription_asked_faster_than_the_fastest_interval_still_gets_each_change_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Revised to the fastest interval, a 0 ms subscription still gets a change in the turn it was
    made (decision 76), not at the revised interval's next tick: here the fastest interval is made
    five seconds long, and the change arrives far sooner."""
    from uacell.ua import subscriptions

    monkeypatch.setattr(subscriptions, "FASTEST_PUBLISHING_INTERVAL", 5000.0)
    async with serving(fast_config(tmp_path / "data")) as (app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        values = Values()
        subscription = await client.create_subscription(0, values)
        served = app.server.iserver.subscription_service.subscriptions[subscription.subscription_id]
        assert served.data.RevisedPublishingInterval == 5000.0
        await subscription.subscribe_data_change(client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns)))
        await wait_until(lambda: len(values.seen) == 1, timeout=10)
        filler = client.get_node(ua.NodeId("Filler1", ns))
        called = time.monotonic()
        await filler.call_method(ua.NodeId("Filler1.SetMachSpeed", ns), ua.Variant(75.0, ua.VariantType.Float))
        await wait_until(lambda: len(values.seen) == 2, timeout=10)
        assert values.seen[-1] == 75.0 and time.monotonic() - called < 2.5  # not at the 5 s tick
        await subscription.delete()


async def test_a_client_gets_at_most_its_max_notifications_per_publish_in_one_message(tmp_path: Path) -> None:
    """OPC 10000-4 5.13.2: MaxNotificationsPerPublish is the most notifications a client wishes to
    receive in one Publish response; the rest follow (MoreNotifications). asyncua sent every queued
    notification in one message."""
    names = ("MachSpeed", "CurMachSpeed", "UnitModeCurrent", "StateCurrent", "EquipmentBlocked")
    async with serving(fast_config(tmp_path / "data")) as (_app, client):
        ns = await client.get_namespace_index("urn:uacell:cell")
        seen: list[tuple[int, str]] = []  # (the message's sequence number, the variable)
        nodes = {}
        for name in names:
            node = client.get_node(ua.NodeId(f"Filler1.Status.{name}", ns))
            with contextlib.suppress(ua.UaStatusCodeError):
                await node.read_value()
                nodes[node.nodeid] = name
        assert len(nodes) >= 4  # enough to need three messages of two

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                seen.append((subscription.last_sequence_number, nodes[node.nodeid]))

        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=100,
            RequestedLifetimeCount=300,
            RequestedMaxKeepAliveCount=10,
            MaxNotificationsPerPublish=2,
            PublishingEnabled=True,
        )
        subscription = await client.create_subscription(params, Handler())
        await subscription.subscribe_data_change([client.get_node(n) for n in nodes])  # one request: all queued
        await wait_until(lambda: len(seen) == len(nodes), timeout=10)
        assert sorted(name for _, name in seen) == sorted(nodes.values())  # each once, none lost
        per_message = [sum(1 for seq, _ in seen if seq == s) for s in sorted({seq for seq, _ in seen})]
        assert max(per_message) == 2 and len(per_message) == (len(nodes) + 1) // 2, seen
        await subscription.delete()
