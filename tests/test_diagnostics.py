"""OPC UA server diagnostics and Server.GetMonitoredItems, read through asyncua and node-opcua."""

from __future__ import annotations

import asyncio
import time

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, run_node, start_app

module_loop = pytest.mark.asyncio(loop_scope="module")
pytestmark = module_loop

PASSWORD = "correct horse battery"
TIMEOUT = 30.0
OID = ua.ObjectIds
SECURITY_ARRAY = OID.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionSecurityDiagnosticsArray


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory):
    server = await start_app(fast_config(tmp_path_factory.mktemp("diag") / "data"))
    server.users.add("root", "admin", PASSWORD)
    try:
        yield server
    finally:
        await server.stop()


async def read(client: Client, node_id: int):
    return await client.get_node(ua.NodeId(node_id)).read_value()


async def until(probe, predicate, timeout: float = TIMEOUT):
    deadline = time.monotonic() + timeout
    while True:
        value = await probe()
        if predicate(value):
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met; last value {value!r}")
        await asyncio.sleep(0.1)


def mine(sessions, name: str):
    """The entries of the session whose client calls itself ``name`` (asyncua: ``Client.name``)."""
    return [s for s in sessions if s.ClientDescription.ApplicationName.Text == name]


async def test_enabled_flag_and_summary_follow_sessions_and_subscriptions(app):
    async with Client(app.endpoint, timeout=20) as first:
        assert await read(first, OID.Server_ServerDiagnostics_EnabledFlag) is True
        assert await read(first, OID.Server_ServerStatus_State) == ua.ServerState.Running
        before = await read(first, OID.Server_ServerDiagnostics_ServerDiagnosticsSummary)
        assert before.CurrentSessionCount >= 1
        second = Client(app.endpoint, timeout=20)
        await second.connect()
        try:
            await second.create_subscription(250, None)
            summary = await until(
                lambda: read(first, OID.Server_ServerDiagnostics_ServerDiagnosticsSummary),
                lambda s: (
                    s.CumulatedSessionCount == before.CumulatedSessionCount + 1
                    and s.CurrentSubscriptionCount == before.CurrentSubscriptionCount + 1
                ),
            )
            assert summary.CurrentSessionCount == before.CurrentSessionCount + 1
            assert summary.CumulatedSubscriptionCount == before.CumulatedSubscriptionCount + 1
            component = OID.Server_ServerDiagnostics_ServerDiagnosticsSummary_CurrentSessionCount
            assert await read(first, component) == summary.CurrentSessionCount
        finally:
            await second.disconnect()
        await until(
            lambda: read(first, OID.Server_ServerDiagnostics_ServerDiagnosticsSummary),
            lambda s: s.CurrentSessionCount == before.CurrentSessionCount,
        )


async def test_a_refused_login_counts_as_a_rejected_session(app):
    async with Client(app.endpoint, timeout=20) as observer:
        before = await read(observer, OID.Server_ServerDiagnostics_ServerDiagnosticsSummary)
        bad = Client(app.endpoint, timeout=20)
        bad.set_user("root")
        bad.set_password("wrong")
        with pytest.raises(ua.UaStatusCodeError):
            await bad.connect()
        app.security.throttle.succeeded("root", "127.0.0.1")
        after = await until(
            lambda: read(observer, OID.Server_ServerDiagnostics_ServerDiagnosticsSummary),
            lambda s: s.RejectedSessionCount == before.RejectedSessionCount + 1,
        )
        assert after.SecurityRejectedSessionCount == before.SecurityRejectedSessionCount + 1
        assert after.SecurityRejectedRequestsCount == before.SecurityRejectedRequestsCount + 1


async def test_session_diagnostics_count_each_service(app):
    client = Client(app.endpoint, timeout=20)
    client.name = "diagnosed session"
    async with client:
        sub = await client.create_subscription(250, None)
        await sub.subscribe_data_change(client.get_node(ua.NodeId(OID.Server_ServerStatus_CurrentTime)))
        server = client.get_node(ua.NodeId(OID.Server))
        await server.call_method(
            ua.NodeId(OID.Server_GetMonitoredItems), ua.Variant(sub.subscription_id, ua.VariantType.UInt32)
        )
        probe = lambda: read(client, OID.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionDiagnosticsArray)  # noqa: E731
        sessions = await until(
            probe,
            lambda arr: (
                bool(mine(arr, "diagnosed session"))
                and mine(arr, "diagnosed session")[0].CallCount.TotalCount == 1
                and mine(arr, "diagnosed session")[0].ReadCount.TotalCount >= 1  # the probe's own reads
            ),
        )
        (d,) = mine(sessions, "diagnosed session")
        assert d.ClientDescription.ApplicationUri == client.application_uri
        assert d.EndpointUrl == app.endpoint
        assert d.CurrentSubscriptionsCount == 1 and d.CurrentMonitoredItemsCount == 1
        assert d.CreateSubscriptionCount.TotalCount == 1 and d.CreateMonitoredItemsCount.TotalCount == 1
        assert d.ReadCount.TotalCount >= 1
        assert d.TotalRequestCount.TotalCount >= d.ReadCount.TotalCount + 3
        assert d.ServerUri == app.server.get_application_uri()
    async with Client(app.endpoint, timeout=20) as other:
        gone = await read(other, OID.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionDiagnosticsArray)
        assert mine(gone, "diagnosed session") == []


async def test_session_security_diagnostics_are_for_admins_only(app):
    async with Client(app.endpoint, timeout=20) as anonymous:
        with pytest.raises(ua.UaStatusCodeError) as err:
            await read(anonymous, SECURITY_ARRAY)
        assert err.value.code == ua.StatusCodes.BadUserAccessDenied
    admin = Client(app.endpoint, timeout=20)
    admin.set_user("root")
    admin.set_password(PASSWORD)
    async with admin:
        node = SECURITY_ARRAY
        entries = await until(
            lambda: read(admin, node), lambda arr: any(e.ClientUserIdOfSession == "root" for e in arr)
        )
        (mine_,) = [e for e in entries if e.ClientUserIdOfSession == "root"]
        assert mine_.AuthenticationMechanism == "UserName"
        assert mine_.ClientUserIdHistory == ["root"]
        assert mine_.SecurityMode == ua.MessageSecurityMode.None_
        assert mine_.SecurityPolicyUri == "http://opcfoundation.org/UA/SecurityPolicy#None"
        assert mine_.TransportProtocol == "opc.tcp" and mine_.TransportEncoding == "UA Binary"


async def test_get_monitored_items_answers_for_the_callers_own_subscription(app):
    async with Client(app.endpoint, timeout=20) as client, Client(app.endpoint, timeout=20) as stranger:
        sub = await client.create_subscription(250, None)
        nodes = [
            client.get_node(ua.NodeId(n)) for n in (OID.Server_ServerStatus_CurrentTime, OID.Server_ServerStatus_State)
        ]
        handles = await sub.subscribe_data_change(nodes)
        server = client.get_node(ua.NodeId(OID.Server))
        method = ua.NodeId(OID.Server_GetMonitoredItems)
        sid = ua.Variant(sub.subscription_id, ua.VariantType.UInt32)
        server_handles, client_handles = await server.call_method(method, sid)
        assert sorted(server_handles) == sorted(handles)
        # what asyncua sent as ClientHandle for each item (it keys its items by them)
        expected_client = sorted(c for c, item in sub._monitored_items.items() if item.server_handle in handles)
        assert len(expected_client) == 2
        assert sorted(client_handles) == expected_client

        req = ua.CallMethodRequest(ObjectId=ua.NodeId(OID.Server), MethodId=method, InputArguments=[sid])
        (res,) = await stranger.uaclient.call([req])
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
        req.InputArguments = [ua.Variant(987654, ua.VariantType.UInt32)]
        (res,) = await client.uaclient.call([req])
        assert res.StatusCode.value == ua.StatusCodes.BadSubscriptionIdInvalid
        req.InputArguments = [ua.Variant("1", ua.VariantType.String)]
        (res,) = await client.uaclient.call([req])
        assert res.StatusCode.value == ua.StatusCodes.BadTypeMismatch


@pytest.mark.interop
async def test_node_opcua_reads_the_diagnostics_and_gets_monitored_items(app):
    out = await asyncio.to_thread(run_node, "diagnostics.js", app.endpoint, "root", PASSWORD)
    assert out["enabledFlag"] is True
    assert out["summary"]["currentSessionCount"] >= 1
    assert out["summary"]["currentSubscriptionCount"] >= 1
    (me,) = [s for s in out["sessions"] if s["sessionName"] == "uacell diagnostics probe"]
    assert me["currentSubscriptionsCount"] == 1 and me["currentMonitoredItemsCount"] == 1
    assert out["monitoredItems"]["statusCode"] == "Good"
    assert out["monitoredItems"]["serverHandles"] == [out["monitoredItemId"]]
    assert out["monitoredItems"]["clientHandles"] == [out["clientHandle"]]
    assert out["unknownSubscription"] == "BadSubscriptionIdInvalid"
    assert out["securityAnonymous"] == "BadUserAccessDenied"
    admin = [e for e in out["securityAdmin"] if e["clientUserIdOfSession"] == "root"]
    assert admin == [
        {
            "clientUserIdOfSession": "root",
            "authenticationMechanism": "UserName",
            "encoding": "UA Binary",
            "transportProtocol": "opc.tcp",
            "securityPolicyUri": "http://opcfoundation.org/UA/SecurityPolicy#None",
        }
    ]
