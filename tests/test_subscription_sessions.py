"""A subscription belongs to its session (OPC 10000-4 5.14, decision 80), through a server with several
asyncua clients over TCP.

Written from the standard's text: each service that names a subscription answers Bad_SubscriptionIdInvalid
for one the session does not own (5.13 and 5.14, "Bad_SubscriptionIdInvalid"); Publish answers
Bad_NoSubscription when the session has none (5.14.5); Republish Bad_MessageNotAvailable when the message
is not in the retransmission queue (5.14.6); TransferSubscriptions moves a subscription only to a session
of the same user, answers Bad_NothingToDo for one the session already owns, and tells the old session
Good_SubscriptionTransferred (5.14.7). asyncua served any session's request for any subscription.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until

from uacell.server import UacellServer
from uacell.ua.subscriptions import Identity, revised_counts, revised_interval

PASSWORD = "correct horse battery"
TIMEOUT = 30.0
SC = ua.StatusCodes


class Seen:
    """A subscription handler that keeps what it is sent."""

    def __init__(self) -> None:
        self.values: list[Any] = []
        self.status: list[int] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.append(val)

    def status_change_notification(self, status: Any) -> None:
        self.status.append(status.Status.value)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[UacellServer]:
    server = await start_app(fast_config(tmp_path_factory.mktemp("subs") / "data"))
    server.users.add("eng", "engineer", PASSWORD)
    server.users.add("op", "operator", PASSWORD)
    try:
        yield server
    finally:
        await server.stop()


def client_of(app: UacellServer, user: str | None = None) -> Client:
    client = Client(app.endpoint, timeout=TIMEOUT, watchdog_intervall=30.0)
    if user is not None:
        client.set_user(user)
        client.set_password(PASSWORD)
    return client


async def mach_speed(client: Client) -> Any:
    ns = await client.get_namespace_index("urn:uacell:cell")
    return client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns))


def params(interval: float = 100.0) -> ua.CreateSubscriptionParameters:
    return ua.CreateSubscriptionParameters(
        RequestedPublishingInterval=interval, RequestedLifetimeCount=30, RequestedMaxKeepAliveCount=3,
        PublishingEnabled=True,
    )  # fmt: skip


async def set_speed(client: Client, speed: float) -> None:
    ns = await client.get_namespace_index("urn:uacell:cell")
    filler = client.get_node(ua.NodeId("Filler1", ns))
    await filler.call_method(ua.NodeId("Filler1.SetMachSpeed", ns), ua.Variant(speed, ua.VariantType.Float))


async def fault(request: Any) -> int:
    """The status code of a request the server answers with a ServiceFault."""
    with pytest.raises(ua.UaStatusCodeError) as err:
        await request
    return int(err.value.code)


def test_revised_values_follow_the_standard() -> None:
    assert revised_interval(0.0) == (50.0, True) and revised_interval(float("nan")) == (50.0, True)
    assert revised_interval(250.0) == (250.0, False)
    assert revised_interval(float("inf")) == (3_600_000.0, False)
    assert revised_counts(0, 0, 15_000, 5_000) == (15_000, 5_000)
    assert revised_counts(10, 10, 15_000, 5_000) == (30, 10)  # the lifetime at least three keep-alives
    assert revised_counts(100_000, 9_000, 15_000, 5_000) == (15_000, 5_000)


def test_who_may_take_over_a_subscription() -> None:
    none, sign = ua.MessageSecurityMode.None_, ua.MessageSecurityMode.Sign
    eng = Identity("eng", "urn:a", none)
    assert eng.may_take_from(Identity("eng", "urn:b", none))  # the same user, from any application
    assert not Identity("op", "urn:a", none).may_take_from(eng)
    assert not Identity(None, "urn:a", none).may_take_from(eng)
    # anonymous: the same application, over signed channels
    assert Identity(None, "urn:a", sign).may_take_from(Identity(None, "urn:a", sign))
    assert not Identity(None, "urn:a", none).may_take_from(Identity(None, "urn:a", none))
    assert not Identity(None, "urn:b", sign).may_take_from(Identity(None, "urn:a", sign))
    assert not Identity(None, "", sign).may_take_from(Identity(None, "", sign))


@pytest.mark.asyncio(loop_scope="module")
async def test_another_sessions_subscription_is_not_known(app: UacellServer) -> None:
    seen = Seen()
    async with client_of(app) as owner, client_of(app) as other:
        node = await mach_speed(owner)
        sub = await owner.create_subscription(params(), seen)
        handle = await sub.subscribe_data_change(node)
        await wait_until(lambda: len(seen.values) == 1)
        sid = sub.subscription_id
        mid = handle  # the MonitoredItemId
        them = other.uaclient
        item = ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=node.nodeid, AttributeId=ua.AttributeIds.Value),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=ua.MonitoringParameters(ClientHandle=7, SamplingInterval=0, QueueSize=1),
        )
        create = ua.CreateMonitoredItemsParameters(SubscriptionId=sid, ItemsToCreate=[item])
        assert await fault(them.create_monitored_items(create)) == SC.BadSubscriptionIdInvalid
        change_item = ua.MonitoredItemModifyRequest(MonitoredItemId=mid, RequestedParameters=ua.MonitoringParameters())
        modify = ua.ModifyMonitoredItemsParameters(SubscriptionId=sid, ItemsToModify=[change_item])
        assert await fault(them.modify_monitored_items(modify)) == SC.BadSubscriptionIdInvalid
        mode = ua.SetMonitoringModeParameters(
            SubscriptionId=sid, MonitoringMode=ua.MonitoringMode.Disabled, MonitoredItemIds=[mid]
        )
        assert await fault(them.set_monitoring_mode(mode)) == SC.BadSubscriptionIdInvalid
        delete_items = ua.DeleteMonitoredItemsParameters(SubscriptionId=sid, MonitoredItemIds=[mid])
        assert await fault(them.delete_monitored_items(delete_items)) == SC.BadSubscriptionIdInvalid
        change = ua.ModifySubscriptionParameters(SubscriptionId=sid, RequestedPublishingInterval=60_000.0)
        assert await fault(them.update_subscription(change)) == SC.BadSubscriptionIdInvalid
        republish = ua.RepublishParameters(SubscriptionId=sid, RetransmitSequenceNumber=1)
        request = ua.RepublishRequest(Parameters=republish)
        assert await fault(them.protocol.send_request(request)) == SC.BadSubscriptionIdInvalid
        off = ua.SetPublishingModeParameters(PublishingEnabled=False, SubscriptionIds=[sid])
        assert [s.value for s in await them.set_publishing_mode(off)] == [SC.BadSubscriptionIdInvalid]
        assert [s.value for s in await them.delete_subscriptions([sid])] == [SC.BadSubscriptionIdInvalid]
        # OPC 10000-9 5.5.7: ConditionRefresh of a subscription of one's own
        condition_type, refresh = (
            ua.NodeId(ua.ObjectIds.ConditionType),
            ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
        )
        arg = ua.Variant(sid, ua.VariantType.UInt32)
        (theirs,) = await them.call(
            [ua.CallMethodRequest(ObjectId=condition_type, MethodId=refresh, InputArguments=[arg])]
        )
        (own,) = await owner.uaclient.call([ua.CallMethodRequest(condition_type, refresh, [arg])])
        assert (theirs.StatusCode.value, own.StatusCode.value) == (SC.BadSubscriptionIdInvalid, SC.Good)
        # a session without a subscription of its own: Publish has nothing to wait for
        assert await fault(them.publish([])) == SC.BadNoSubscription

        served = app.server.iserver.subscription_service.subscriptions[sid]
        assert served.data.RevisedPublishingInterval == 100.0 and served._publishing_enabled
        # the owner's subscription is whole: its item still reports
        await set_speed(owner, 77.0)
        await wait_until(lambda: seen.values[-1:] == [77.0])
        await sub.delete()


@pytest.mark.asyncio(loop_scope="module")
async def test_acknowledgements_and_republish_are_the_sessions_own(app: UacellServer) -> None:
    async with client_of(app) as owner, client_of(app) as other:
        mine = await owner.create_subscription(params(), Seen())
        theirs = await other.create_subscription(params(), Seen())
        ack = ua.SubscriptionAcknowledgement(SubscriptionId=mine.subscription_id, SequenceNumber=1)
        unknown = ua.SubscriptionAcknowledgement(SubscriptionId=theirs.subscription_id, SequenceNumber=999_999)
        response = await other.uaclient.publish([ack, unknown])
        results = [s.value for s in response.Parameters.Results]
        assert results == [SC.BadSubscriptionIdInvalid, SC.BadSequenceNumberUnknown]
        republish = ua.RepublishParameters(SubscriptionId=theirs.subscription_id, RetransmitSequenceNumber=999_999)
        request = ua.RepublishRequest(Parameters=republish)
        assert await fault(other.uaclient.protocol.send_request(request)) == SC.BadMessageNotAvailable
        await mine.delete()
        await theirs.delete()


@pytest.mark.asyncio(loop_scope="module")
async def test_a_subscription_goes_only_to_a_session_of_the_same_user(app: UacellServer) -> None:
    seen = Seen()
    async with client_of(app, "eng") as first, client_of(app, "eng") as second, client_of(app, "op") as stranger:
        node = await mach_speed(first)
        sub = await first.create_subscription(params(), seen)
        await sub.subscribe_data_change(node)
        await wait_until(lambda: len(seen.values) == 1)
        sid = sub.subscription_id

        async def transfer(client: Client, *ids: int) -> list[int]:
            request = ua.TransferSubscriptionsParameters(SubscriptionIds=list(ids), SendInitialValues=True)
            return [r.StatusCode.value for r in await client.uaclient.transfer_subscriptions(request)]

        assert await transfer(stranger, sid) == [SC.BadUserAccessDenied]
        assert await transfer(first, sid) == [SC.BadNothingToDo]
        assert await transfer(second, 4_000_000) == [SC.BadSubscriptionIdInvalid]
        async with client_of(app) as anonymous:
            assert await transfer(anonymous, sid) == [SC.BadUserAccessDenied]

        assert await transfer(second, sid) == [SC.Good]
        # the old session is told, with a Publish request it had waiting
        await wait_until(lambda: seen.status == [SC.GoodSubscriptionTransferred])
        # the new one gets the current value at once (SendInitialValues), then the changes
        response = await second.uaclient.publish([])
        assert response.Parameters.SubscriptionId == sid
        (data,) = response.Parameters.NotificationMessage.NotificationData
        assert [i.Value.Value.Value for i in data.MonitoredItems] == [seen.values[-1]]
        await set_speed(second, 61.0)
        response = await second.uaclient.publish([])
        (data,) = response.Parameters.NotificationMessage.NotificationData
        assert [i.Value.Value.Value for i in data.MonitoredItems] == [61.0]
        await asyncio.sleep(0)  # nothing for the old session's handler since
        assert 61.0 not in seen.values
        assert await transfer(first, sid) == [SC.Good]  # and back, the same user
        assert [s.value for s in await first.uaclient.delete_subscriptions([sid])] == [SC.Good]


@pytest.mark.asyncio(loop_scope="module")
async def test_resend_data_sends_the_current_values_again_to_its_own_session(app: UacellServer) -> None:
    """OPC 10000-5 9.3: Server.ResendData(SubscriptionId) has the next Publish carry the current value of
    each data item in Reporting mode, changed or not; Bad_UserAccessDenied when the subscription is
    another session's, Bad_SubscriptionIdInvalid when there is none. asyncua answered Bad_NotImplemented."""
    resend = ua.NodeId(ua.ObjectIds.Server_ResendData)
    async with client_of(app) as owner, client_of(app) as other:
        seen, sampled = Seen(), Seen()
        sub = await owner.create_subscription(params(), seen)
        await sub.subscribe_data_change(await mach_speed(owner))
        quiet = await owner.create_subscription(params(), sampled)
        await quiet.subscribe_data_change(await mach_speed(owner), monitoring=ua.MonitoringMode.Sampling)
        await wait_until(lambda: len(seen.values) == 1)
        server = owner.get_node(ua.ObjectIds.Server)
        await server.call_method(resend, ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
        await wait_until(lambda: len(seen.values) == 2)
        assert seen.values[1] == seen.values[0]  # the same value, sent again
        await server.call_method(resend, ua.Variant(quiet.subscription_id, ua.VariantType.UInt32))
        for sid, code in ((sub.subscription_id, SC.BadUserAccessDenied), (987654, SC.BadSubscriptionIdInvalid)):
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await other.get_node(ua.ObjectIds.Server).call_method(resend, ua.Variant(sid, ua.VariantType.UInt32))
            assert refused.value.code == code
        speed = seen.values[0] + 1.5
        await set_speed(owner, speed)  # a change after: it arrives, and nothing more was resent meanwhile
        await wait_until(lambda: len(seen.values) == 3)
        assert seen.values == [seen.values[0], seen.values[0], speed]
        assert sampled.values == []  # an item in Sampling mode reports nothing
