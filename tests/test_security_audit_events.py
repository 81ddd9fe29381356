"""The audit events of the Session Service Set and of refused certificates, through a real asyncua client
over TCP (OPC 10000-4 6.5.6: a server that audits "shall generate audit Events for both successful and
failed Service invocations"; OPC 10000-5 6.4.7 to 6.4.19 for their fields). Only admin sessions get
them (decision 94)."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto import security_policies as sp
from conftest import fast_config, start_app
from cryptography.hazmat.primitives.asymmetric import rsa
from helpers import Collector, call_path, secure_client
from plant_ca import Authority, der
from uaraw import RawClient, Refused, anonymous_token

from uacell.core.roles import Role
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

OBJ = ua.ObjectIds
PASSWORD = "audit-events-pw-1"
AUDIT_TYPES = [
    OBJ.AuditUpdateStateEventType,  # which every session may see: the operator's subscription gets these
    OBJ.AuditOpenSecureChannelEventType,
    OBJ.AuditChannelEventType,
    OBJ.AuditCreateSessionEventType,
    OBJ.AuditActivateSessionEventType,
    OBJ.AuditSessionEventType,
    OBJ.AuditCertificateUntrustedEventType,
]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[UacellServer]:
    app = await start_app(fast_config(tmp_path_factory.mktemp("audit-events") / "data"))
    app.users.add("ada", Role.ADMIN, PASSWORD)
    app.users.add("otto", Role.OPERATOR, PASSWORD)
    try:
        yield app
    finally:
        await app.stop()


async def listener(app: UacellServer, user: str) -> tuple[Client, Collector]:
    """A session of ``user`` subscribed to the Server object's audit events."""
    client = Client(app.endpoint, timeout=20)
    client.set_user(user)
    client.set_password(PASSWORD)
    await client.connect()
    collector = Collector()
    sub = await client.create_subscription(0, collector)
    evtypes = [client.get_node(ua.NodeId(t)) for t in AUDIT_TYPES]
    await sub.subscribe_events(client.nodes.server, evtypes)
    return client, collector


async def transition(client: Client) -> None:
    """A transition of Filler1 the client causes: Stop, or Reset where Stop is not allowed."""
    machine = "Filler1.BaseStateMachine.MachineState"
    if not (await call_path(client, machine, "Stop")).StatusCode.is_good():
        assert (await call_path(client, machine, "Reset")).StatusCode.is_good()


def of(type_id: int, source: str, *, status: bool | None = None, session: Any = None, message: str = "") -> Any:
    """Matches an event of that type and SourceName (and Status, SessionId, a part of its Message)."""

    def match(e: Any) -> bool:
        return (
            e.EventType == ua.NodeId(type_id)
            and e.SourceName == source
            and (status is None or e.Status is status)
            and (session is None or e.SessionId == session)
            and message in (e.Message.Text or "")
        )

    return match


async def test_a_session_from_start_to_end_is_audited_for_admins_only(server: UacellServer) -> None:
    admin, seen = await listener(server, "ada")
    operator, not_seen = await listener(server, "otto")
    try:
        client = Client(server.endpoint, timeout=20)
        client.description = "audited client"
        await client.connect()
        await client.disconnect()

        created = await seen.wait_for(
            of(OBJ.AuditCreateSessionEventType, "Session/CreateSession", message="audited client")
        )
        assert created.Status is True
        assert created.ClientUserId == "System/CreateSession"
        assert created.SourceNode == ua.NodeId(OBJ.Server)
        assert created.ServerId == server.server.get_application_uri()
        assert created.RevisedSessionTimeout > 0
        assert created.ClientCertificate is None  # a SecurityPolicy None channel: no certificate plays a part
        assert created.SecureChannelId
        assert not created.SessionId.is_null()  # the new session's id
        activated = await seen.wait_for(
            lambda e: (
                of(OBJ.AuditActivateSessionEventType, "Session/ActivateSession")(e) and e.SessionId == created.SessionId
            )
        )
        assert activated.Status is True
        assert isinstance(activated.UserIdentityToken, ua.AnonymousIdentityToken)
        assert activated.SecureChannelId == created.SecureChannelId
        closed = await seen.wait_for(of(OBJ.AuditSessionEventType, "Session/CloseSession", session=created.SessionId))
        assert closed.Status is True
        # the operator's subscription gets the audit event of its own Reset, and none of the sessions'
        await transition(operator)
        await not_seen.wait_for(lambda e: e.EventType == ua.NodeId(OBJ.AuditUpdateStateEventType))
        assert {e.EventType for e in not_seen.events} == {ua.NodeId(OBJ.AuditUpdateStateEventType)}
    finally:
        await operator.disconnect()
        await admin.disconnect()


async def test_a_refused_password_is_audited_without_the_password(server: UacellServer) -> None:
    admin, seen = await listener(server, "ada")
    try:
        client = Client(server.endpoint, timeout=20)
        client.set_user("otto")
        client.set_password("not the password")
        with pytest.raises(ua.UaStatusCodeError):
            await client.connect()
        refused = await seen.wait_for(
            lambda e: of(OBJ.AuditActivateSessionEventType, "Session/ActivateSession")(e) and not e.Status
        )
        assert refused.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        assert refused.ClientUserId == "otto"
        token = refused.UserIdentityToken
        assert isinstance(token, ua.UserNameIdentityToken)
        assert token.UserName == "otto" and token.Password is None and token.EncryptionAlgorithm is None
    finally:
        await admin.disconnect()


async def test_a_refused_certificate_fires_its_certificate_event_and_a_failed_create(
    server: UacellServer, tmp_path: Path
) -> None:
    admin, seen = await listener(server, "ada")
    try:
        # a certificate nobody trusts, with its CA's chain
        ca = Authority.root("Stranger CA", key_index=4)
        cert, key = ca.application("urn:stranger", "Stranger", key_index=5)
        client = await secure_client(server.endpoint, tmp_path, cert, key, "urn:stranger")
        with pytest.raises(ua.UaStatusCodeError):
            await client.connect()
        untrusted = await seen.wait_for(of(OBJ.AuditCertificateUntrustedEventType, "Security/Certificate"))
        assert untrusted.Certificate == der(cert)
        assert untrusted.Status is False
        # its issuer is nowhere: the precise step here, what the client was told in the session's event
        assert untrusted.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadCertificateChainIncomplete)
        failed = await seen.wait_for(
            lambda e: of(OBJ.AuditCreateSessionEventType, "Session/CreateSession")(e) and not e.Status
        )
        assert failed.SessionId == ua.NodeId()  # "null for a failed CreateSession"
        assert failed.ClientCertificate == der(cert)
        assert failed.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadSecurityChecksFailed)
    finally:
        await admin.disconnect()


async def connected(server: UacellServer, seen: Collector, name: str) -> tuple[Client, Any]:
    """An anonymous client whose session is named after ``name``, and the audit event of its CreateSession."""
    client = Client(server.endpoint, timeout=20)
    client.description = name
    await client.connect()
    created = await seen.wait_for(
        of(OBJ.AuditCreateSessionEventType, "Session/CreateSession", status=True, message=name)
    )
    return client, created


async def test_a_lost_connection_ends_its_session_as_terminated(server: UacellServer) -> None:
    admin, seen = await listener(server, "ada")
    try:
        client, created = await connected(server, seen, "vanishing client")
        client.disconnect_socket()  # no CloseSession: the transport goes
        await seen.wait_for(of(OBJ.AuditSessionEventType, "Session/Terminated", session=created.SessionId))
    finally:
        await admin.disconnect()


async def test_a_secure_channel_opened_and_closed_is_audited(server: UacellServer) -> None:
    admin, seen = await listener(server, "ada")
    try:
        client, created = await connected(server, seen, "channel client")
        channel = created.SecureChannelId
        await client.disconnect()
        opened = await seen.wait_for(
            lambda e: (
                of(OBJ.AuditOpenSecureChannelEventType, "SecureChannel/OpenSecureChannel", status=True)(e)
                and e.SecureChannelId == channel
            )
        )
        assert opened.ClientUserId == "System/OpenSecureChannel"
        assert opened.SecurityPolicyUri == "http://opcfoundation.org/UA/SecurityPolicy#None"
        assert opened.SecurityMode == ua.MessageSecurityMode.None_
        assert opened.RequestType == ua.SecurityTokenRequestType.Issue
        assert opened.RequestedLifetime > 0
        assert opened.ClientCertificate is None
        closed = await seen.wait_for(
            lambda e: (
                of(OBJ.AuditChannelEventType, "SecureChannel/CloseSecureChannel")(e) and e.SecureChannelId == channel
            )
        )
        assert closed.Status is True
        assert seen.events.index(opened) < seen.events.index(created) < seen.events.index(closed)
    finally:
        await admin.disconnect()


async def test_a_refused_secure_channel_is_audited(server: UacellServer) -> None:
    """A mode no endpoint offers (policy None with Sign): refused, and audited as such."""
    admin, seen = await listener(server, "ada")
    try:
        async with await RawClient.connect(
            "127.0.0.1", server.config.server.port, policy=sp.SecurityPolicyNone()
        ) as raw:
            await raw.hello()
            with pytest.raises(Refused):
                await raw.open_channel(mode=ua.MessageSecurityMode.Sign)
        refused = await seen.wait_for(
            of(OBJ.AuditOpenSecureChannelEventType, "SecureChannel/OpenSecureChannel", status=False)
        )
        assert refused.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadSecurityModeRejected)
        assert refused.SecureChannelId == ""
        assert refused.SecurityMode == ua.MessageSecurityMode.Sign
    finally:
        await admin.disconnect()


async def test_an_open_secure_channel_signed_with_another_key_is_refused_and_audited(
    server: UacellServer, caplog: pytest.LogCaptureFixture
) -> None:
    """Decision 106: a client that holds a certificate but not its private key (the certificate travels in
    clear in every OpenSecureChannel) signs with a key of its own. OPC 10000-6 6.7.4: "The Server shall
    validate the Message and the ClientCertificate"; the signature does not verify, so the channel is
    refused with an Error message (Bad_SecurityChecksFailed), and OPC 10000-4 6.5.5's audit event tells
    an admin which certificate was used. Before, asyncua's InvalidSignature reached the log as a traceback
    at ERROR, the client was sent nothing and waited for the handshake timeout, and nothing was audited."""
    admin, seen = await listener(server, "ada")
    try:
        server_der = (server.data_dir / "pki" / "own" / "cert.der").read_bytes()
        ca = Authority.root("Someone Else's CA", key_index=6)
        cert, _their_key = ca.application("urn:someone", "Someone", key_index=7)
        forger = rsa.generate_private_key(public_exponent=65537, key_size=2048)
        policy = sp.SecurityPolicyBasic256Sha256(server_der, cert, forger, ua.MessageSecurityMode.SignAndEncrypt)
        async with await RawClient.connect("127.0.0.1", server.config.server.port, policy=policy) as raw:
            await raw.hello()
            with pytest.raises(Refused) as refused:
                await raw.open_channel()
            assert refused.value.code == ua.StatusCodes.BadSecurityChecksFailed
            assert await raw.at_eof()
        audited = await seen.wait_for(
            lambda e: (
                of(OBJ.AuditOpenSecureChannelEventType, "SecureChannel/OpenSecureChannel", status=False)(e)
                and e.ClientCertificate == der(cert)
            )
        )
        assert audited.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadSecurityChecksFailed)
        assert audited.SecurityPolicyUri == sp.SecurityPolicyBasic256Sha256.URI
        assert audited.SecureChannelId == ""
        assert "signature" in audited.Message.Text
        assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []
    finally:
        await admin.disconnect()


async def test_a_session_that_stops_being_admin_stops_receiving_them(server: UacellServer) -> None:
    """ActivateSession changes the session's user to an operator: the audit events of sessions stop (the
    event of that very change included: it is fired once the session is the operator's)."""
    admin, seen = await listener(server, "ada")
    try:
        client, created = await connected(server, seen, "before the change")
        await client.disconnect()
        await seen.wait_for(  # the last event of that client: nothing of it arrives late below
            lambda e: (
                e.EventType == ua.NodeId(OBJ.AuditChannelEventType) and e.SecureChannelId == created.SecureChannelId
            )
        )
        await admin.activate_session("otto", PASSWORD)  # the same session, another user
        seen.clear()
        client = Client(server.endpoint, timeout=20)
        client.description = "after the change"
        await client.connect()
        await client.disconnect()
        # a transition it caused: its AuditUpdateStateEvent, which every session may see, marks the end
        await transition(admin)
        await seen.wait_for(lambda e: e.EventType == ua.NodeId(OBJ.AuditUpdateStateEventType))
        assert {e.EventType for e in seen.events} == {ua.NodeId(OBJ.AuditUpdateStateEventType)}
    finally:
        await admin.disconnect()


async def test_an_idle_session_ends_as_timed_out(server: UacellServer) -> None:
    """A session nobody uses past its timeout (the shortest the server grants) ends as Session/Timeout."""
    admin, seen = await listener(server, "ada")
    try:
        async with await RawClient.connect("127.0.0.1", server.config.server.port) as raw:
            await raw.hello()
            await raw.open_channel()
            session = await raw.create_session(timeout=0)  # revised to the server's shortest
            await raw.activate_session(anonymous_token())
            assert session.response.RevisedSessionTimeout <= 10000
            ended = await seen.wait_for(
                of(OBJ.AuditSessionEventType, "Session/Timeout", session=session.response.SessionId), timeout=30
            )
            assert ended.Status is True
    finally:
        await admin.disconnect()


async def test_an_activation_whose_client_signature_does_not_verify_is_refused_and_audited(
    server: UacellServer, tmp_path: Path
) -> None:
    """OPC 10000-4 5.7.3.2: the clientSignature proves the client holds its certificate's key; one that does
    not verify is Bad_ApplicationSignatureInvalid (asyncua's check raised, and the client got
    Bad_InternalError with a traceback in the log)."""
    admin, seen = await listener(server, "ada")
    try:
        ca = Authority.root("Audit CA", key_index=6)
        cert, key = ca.application("urn:forger", "Forger", key_index=7)
        (Path(server.data_dir) / "pki" / "trusted" / "forger.der").write_bytes(der(cert))  # trusted by itself
        client = await secure_client(server.endpoint, tmp_path, cert, key, "urn:forger")
        activate = client.activate_session

        async def activate_over_something_else(*args: Any, **kwargs: Any) -> Any:
            client.security_policy.peer_certificate = (client.security_policy.peer_certificate or b"") + b"x"
            return await activate(*args, **kwargs)

        client.activate_session = activate_over_something_else
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await client.connect()
        assert refused.value.code == ua.StatusCodes.BadApplicationSignatureInvalid
        event = await seen.wait_for(
            lambda e: of(OBJ.AuditActivateSessionEventType, "Session/ActivateSession")(e) and not e.Status
        )
        assert event.StatusCodeId == ua.StatusCode(ua.StatusCodes.BadApplicationSignatureInvalid)
    finally:
        await admin.disconnect()
