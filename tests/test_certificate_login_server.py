"""X.509 user certificates over TCP (decision 84): asyncua clients present a user certificate and sign
the server's certificate and nonce with its key, as OPC 10000-4 5.6.3 asks; the server answers with
the status codes of ActivateSession and gives the session the bound user's role."""

from __future__ import annotations

import asyncio
import datetime as dt
import functools
import json
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto import security_policies as sp
from conftest import fast_config, start_app
from cryptography.hazmat.primitives.asymmetric import rsa
from helpers import Collector, wait_until
from test_security import ClientCert, secure_client
from uaraw import Fault, RawClient, none_session
from user_certificates import BASIC256SHA256, RSA_SHA256, UserCertificate, user_certificate

from uacell.security.pki import PkiPaths, TrustList
from uacell.security.users import UserStore, thumbprint
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

OBJ = ua.ObjectIds
OPERATOR = user_certificate("olga, operator")
ADMIN = user_certificate("ada, admin")
STRANGER = user_certificate("somebody")
EXPIRED = user_certificate("old badge", not_before=dt.datetime.now(dt.UTC) - dt.timedelta(days=40), days=30)
SECURITY_ARRAY = ua.NodeId(
    ua.ObjectIds.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionSecurityDiagnosticsArray
)


class Env:
    def __init__(self, app: UacellServer, cert: ClientCert, files: Path) -> None:
        self.app, self.cert, self.files = app, cert, files
        # the command line's store: another object on the same file, as `uacell user` in another process
        self.cli = UserStore.in_data_dir(app.data_dir)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    base = tmp_path_factory.mktemp("certificate-login")
    app = await start_app(fast_config(base / "data"))
    cert = ClientCert(base / "client")
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(cert.der)
    store = UserStore.in_data_dir(app.data_dir)
    store.add("olga", "operator", None, certificate=OPERATOR.der)
    store.add("ada", "admin", None, certificate=ADMIN.der)
    store.add("oldie", "operator", None, certificate=EXPIRED.der)
    try:
        yield Env(app, cert, base / "users")
    finally:
        await app.stop()


async def cert_client(env: Env, user: UserCertificate, *, key_of: UserCertificate | None = None, **kw: Any) -> Client:
    """A Basic256Sha256 SignAndEncrypt client logging in with ``user``'s certificate, signing with the
    key of ``key_of`` (default: its own)."""
    client = await secure_client(env.app, env.cert, connect=False, **kw)
    name = thumbprint(user.der)[:12]
    cert_file, _ = user.write(env.files, name)
    _, key_file = (key_of or user).write(env.files, f"{name}-signer")
    await client.load_client_certificate(str(cert_file))
    await client.load_private_key(key_file)
    await client.connect()
    return client


async def refusal(env: Env, user: UserCertificate, **kw: Any) -> int:
    with pytest.raises(ua.UaStatusCodeError) as err:
        client = await cert_client(env, user, **kw)
        await client.disconnect()
    return int(err.value.code)


async def role_of(client: Client, env: Env) -> str:
    return str(await client.get_node(env.app.security.role_node).read_value())


async def audited_login_event(env: Env, event: str, **fields: Any) -> dict[str, Any]:
    """The last line of ``event`` in the audit trail with ``fields``."""
    path = env.app.data_dir / "audit.log"
    found: list[dict[str, Any]] = []

    def arrived() -> bool:
        text = path.read_text() if path.exists() else ""
        lines = [e for e in map(json.loads, text.splitlines()) if e["event"] == event]
        found[:] = [e for e in lines if fields.items() <= e.items()]
        return bool(found)

    await wait_until(arrived, timeout=20)
    return found[-1]


async def audited_login(env: Env, **fields: Any) -> dict[str, Any]:
    """The last login line of the audit trail with ``fields`` (the trail is written by its own thread)."""
    return await audited_login_event(env, "login", **fields)


async def test_every_endpoint_offers_a_signed_certificate_token(env: Env) -> None:
    async with Client(env.app.endpoint, timeout=20) as client:
        endpoints = await client.get_endpoints()
    assert endpoints
    for endpoint in endpoints:
        (policy,) = [p for p in endpoint.UserIdentityTokens if p.TokenType == ua.UserTokenType.Certificate]
        if endpoint.SecurityMode == ua.MessageSecurityMode.None_:
            # OPC 10000-4 7.41.5: a policy to sign with where the channel has none
            assert policy.SecurityPolicyUri == BASIC256SHA256
        else:
            assert policy.SecurityPolicyUri in ("", endpoint.SecurityPolicyUri)


async def test_a_bound_certificate_logs_in_with_its_users_role(env: Env) -> None:
    client = await cert_client(env, OPERATOR)
    try:
        assert await role_of(client, env) == "operator"
        with pytest.raises(ua.UaStatusCodeError) as err:  # an operator reads no security diagnostics
            await client.get_node(SECURITY_ARRAY).read_value()
        assert err.value.code == ua.StatusCodes.BadUserAccessDenied
    finally:
        await client.disconnect()
    login = await audited_login(env, user="olga")
    assert login["result"] == "Good" and login["address"] == "127.0.0.1"


async def test_session_security_diagnostics_name_the_certificate(env: Env) -> None:
    client = await cert_client(env, ADMIN)
    try:
        assert await role_of(client, env) == "admin"
        deadline = time.monotonic() + 20
        while True:
            entries = await client.get_node(SECURITY_ARRAY).read_value()
            mine = [e for e in entries if e.ClientUserIdOfSession == "ada"]
            if mine or time.monotonic() > deadline:
                break
            await asyncio.sleep(0.05)
        assert [e.AuthenticationMechanism for e in mine] == ["Certificate"]
        assert mine[0].ClientUserIdHistory == ["ada"]
    finally:
        await client.disconnect()


async def test_refusals_by_the_standards_codes(env: Env) -> None:
    assert await refusal(env, STRANGER) == ua.StatusCodes.BadIdentityTokenRejected  # bound to nobody
    assert await refusal(env, OPERATOR, key_of=STRANGER) == ua.StatusCodes.BadUserSignatureInvalid
    assert await refusal(env, EXPIRED) == ua.StatusCodes.BadIdentityTokenRejected
    await audited_login(env, user="oldie", result="BadIdentityTokenRejected")
    await audited_login(env, user=f"certificate {thumbprint(STRANGER.der)}", result="BadIdentityTokenRejected")
    await audited_login(env, user="olga", result="BadUserSignatureInvalid")


async def test_a_refused_user_certificate_fires_its_certificate_event(env: Env) -> None:
    """OPC 10000-4 6.5.6 and OPC 10000-5 6.4.13 to 6.4.19 (decision 102): a user certificate refused after
    it proved its key fires the AuditCertificate subtype of the step that failed, with the certificate,
    besides the failed ActivateSession; a token whose signature does not verify fires none (the
    certificate was not what failed). Only admin sessions receive them (decision 94)."""
    small = user_certificate("olaf, old badge", key=rsa.generate_private_key(public_exponent=65537, key_size=1024))
    env.cli.add("olaf", "operator", None, certificate=small.der)
    admin = await cert_client(env, ADMIN)
    seen = Collector()
    subscription = await admin.create_subscription(0, seen)
    types = [OBJ.AuditCertificateExpiredEventType, OBJ.AuditCertificateUntrustedEventType]
    types += [OBJ.AuditCertificateInvalidEventType, OBJ.AuditActivateSessionEventType]
    await subscription.subscribe_events(admin.nodes.server, [admin.get_node(ua.NodeId(t)) for t in types])
    try:
        refusals = [
            (EXPIRED, OBJ.AuditCertificateExpiredEventType, ua.StatusCodes.BadCertificateTimeInvalid),
            (STRANGER, OBJ.AuditCertificateUntrustedEventType, ua.StatusCodes.BadCertificateUntrusted),
            (small, OBJ.AuditCertificateInvalidEventType, ua.StatusCodes.BadCertificatePolicyCheckFailed),
        ]
        for user, event_type, step in refusals:
            assert await refusal(env, user) == ua.StatusCodes.BadIdentityTokenRejected
            event = await seen.wait_for(functools.partial(_of_certificate, user.der))
            assert event.EventType == ua.NodeId(event_type), user
            assert event.StatusCodeId == ua.StatusCode(step) and event.Status is False
            assert event.SourceName == "Security/Certificate" and event.SourceNode == ua.NodeId(OBJ.Server)
        # what the client was told, in the session's own events
        rejected = ua.StatusCode(ua.StatusCodes.BadIdentityTokenRejected)
        await wait_until(lambda: len([e for e in seen.events if _refused_activation(e, rejected)]) >= 3)
        # signed with another key: the activation's event only
        before = len(seen.events)
        assert await refusal(env, OPERATOR, key_of=STRANGER) == ua.StatusCodes.BadUserSignatureInvalid
        await seen.wait_for(lambda e: _refused_activation(e, ua.StatusCode(ua.StatusCodes.BadUserSignatureInvalid)))
        assert not [e for e in seen.events[before:] if getattr(e, "Certificate", None) is not None]
    finally:
        await admin.disconnect()


def _of_certificate(der: bytes, event: Any) -> bool:
    return bool(getattr(event, "Certificate", None) == der)


def _refused_activation(event: Any, told: ua.StatusCode) -> bool:
    """An AuditActivateSessionEventType of an activation refused with ``told``."""
    return bool(event.EventType == ua.NodeId(OBJ.AuditActivateSessionEventType) and event.StatusCodeId == told)


async def test_other_token_policies_do_not_take_a_certificate(env: Env) -> None:
    client = await secure_client(env.app, env.cert, connect=False)
    cert_file, key_file = OPERATOR.write(env.files, "policy-probe")
    await client.load_client_certificate(str(cert_file))
    await client.load_private_key(key_file)
    original = client.server_policy

    def username_policy(token_type: ua.UserTokenType) -> ua.UserTokenPolicy:
        policy = original(token_type)
        return ua.UserTokenPolicy(
            PolicyId="username", TokenType=policy.TokenType, SecurityPolicyUri=policy.SecurityPolicyUri
        )

    client.server_policy = username_policy
    with pytest.raises(ua.UaStatusCodeError) as err:
        await client.connect()
    assert err.value.code == ua.StatusCodes.BadIdentityTokenInvalid


async def test_a_signed_token_is_good_for_one_activation(env: Env) -> None:
    """The token and signature of one ActivateSession sent again (the same session, a new nonce since)."""
    client = await secure_client(env.app, env.cert, connect=False)
    cert_file, key_file = OPERATOR.write(env.files, "replay")
    await client.load_client_certificate(str(cert_file))
    await client.load_private_key(key_file)
    sent: list[ua.ActivateSessionParameters] = []
    original = client.uaclient.activate_session

    async def recording(params: ua.ActivateSessionParameters) -> ua.ActivateSessionResult:
        sent.append(params)
        return await original(params)

    client.uaclient.activate_session = recording
    await client.connect()
    try:
        assert await role_of(client, env) == "operator"
        first = sent[0]
        again = ua.ActivateSessionParameters(
            # the application's own proof for the new nonce, so that only the user token is replayed
            ClientSignature=ua.SignatureData(
                Algorithm=first.ClientSignature.Algorithm,
                Signature=client.security_policy.asymmetric_cryptography.signature(
                    client.security_policy.peer_certificate + client._server_nonce
                ),
            ),
            UserIdentityToken=first.UserIdentityToken,
            UserTokenSignature=first.UserTokenSignature,
        )
        with pytest.raises(ua.UaStatusCodeError) as err:
            await original(again)
        assert err.value.code == ua.StatusCodes.BadUserSignatureInvalid
        assert await role_of(client, env) == "operator"  # the session goes on as it was
    finally:
        await client.disconnect()


async def test_bindings_made_while_the_server_runs_count_at_the_next_login(env: Env) -> None:
    newcomer = user_certificate("nina")
    assert await refusal(env, newcomer) == ua.StatusCodes.BadIdentityTokenRejected
    env.cli.add("nina", "engineer", "ninas password")
    env.cli.add_certificate("nina", newcomer.der)
    client = await cert_client(env, newcomer)
    try:
        assert await role_of(client, env) == "engineer"
    finally:
        await client.disconnect()
    env.cli.remove_certificate("nina", thumbprint(newcomer.der))
    assert await refusal(env, newcomer) == ua.StatusCodes.BadIdentityTokenRejected


async def test_the_same_identity_may_be_activated_again(env: Env) -> None:
    client = await cert_client(env, OPERATOR, policy=sp.SecurityPolicyBasic256Sha256)
    try:
        assert await role_of(client, env) == "operator"
        await client.activate_session(certificate=client.user_certificate)  # signed for the new nonce
        assert await role_of(client, env) == "operator"
    finally:
        await client.disconnect()


def x509_token(user: UserCertificate, server_certificate: bytes, nonce: bytes) -> tuple[Any, ua.SignatureData]:
    """An X509IdentityToken and its userTokenSignature built by hand from OPC 10000-4 (7.41.5, 5.6.3):
    the None endpoint's certificate policy is Basic256Sha256, whose signature is RSA-PKCS#1 v1.5 SHA-256."""
    token = ua.X509IdentityToken(PolicyId="certificate", CertificateData=user.der)
    signature = ua.SignatureData(Algorithm=RSA_SHA256, Signature=user.sign(server_certificate + nonce))
    return token, signature


async def test_hand_built_tokens_on_a_none_channel_and_a_session_moved(env: Env) -> None:
    port = env.app.config.server.port
    first, session = await none_session("127.0.0.1", port)
    async with first:
        token, signature = x509_token(OPERATOR, session.server_certificate, session.nonce)
        result = await first.activate_session(token, user_signature=signature)
        assert (await first.read_value(env.app.security.role_node)).Value.Value == "operator"
        # the session moves to a new channel only with the same identity (OPC 10000-4 5.6.3.1)
        async with await RawClient.connect("127.0.0.1", port) as second:
            await second.hello()
            await second.open_channel()
            second.auth = first.auth
            token, signature = x509_token(ADMIN, session.server_certificate, result.ServerNonce)
            with pytest.raises(Fault) as refused:
                await second.activate_session(token, user_signature=signature)
            assert refused.value.code == ua.StatusCodes.BadIdentityChangeNotSupported
            token, signature = x509_token(OPERATOR, session.server_certificate, result.ServerNonce)
            await second.activate_session(token, user_signature=signature)
            assert (await second.read_value(env.app.security.role_node)).Value.Value == "operator"


async def test_asyncuas_client_signs_on_a_none_channel_too(env: Env) -> None:
    """The None endpoint's certificate policy is Basic256Sha256: asyncua's Client signs with it there."""
    client = Client(env.app.endpoint, timeout=20)
    cert_file, key_file = OPERATOR.write(env.files, "asyncua-none")
    await client.load_client_certificate(str(cert_file))
    await client.load_private_key(key_file)
    await client.connect()
    try:
        assert await role_of(client, env) == "operator"
    finally:
        await client.disconnect()


async def test_a_session_keeps_its_certificates_user_until_the_certificate_expires(env: Env) -> None:
    """OPC 10000-4 7.41.5 (decision 88): the credentials end when the certificate expires and the session
    stays valid with the anonymous role (operator on loopback); the client renews them with
    ActivateSession and a certificate still valid."""
    # a certificate valid since yesterday, for five more seconds
    short = user_certificate(
        "eve, short badge",
        not_before=dt.datetime.now(dt.UTC) - dt.timedelta(days=1) + dt.timedelta(seconds=5),
        days=1,
    )
    badge = user_certificate("eve, new badge")
    env.cli.add("eve", "engineer", None, certificate=short.der)
    env.cli.add_certificate("eve", badge.der)
    client = await cert_client(env, short)
    try:
        assert await role_of(client, env) == "engineer"
        deadline = time.monotonic() + 30
        while await role_of(client, env) == "engineer" and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        assert await role_of(client, env) == "operator"  # anonymous on loopback: the session goes on
        await audited_login_event(env, "identity_expired", user="eve")
        # renewed with the new badge on the same session
        cert_file, key_file = badge.write(env.files, "eve-new")
        await client.load_client_certificate(str(cert_file))
        await client.load_private_key(key_file)
        await client.activate_session(certificate=client.user_certificate)
        assert await role_of(client, env) == "engineer"
    finally:
        await client.disconnect()


async def wait_for_role(client: Client, env: Env, role: str, timeout: float = 20.0) -> None:
    """Until the session's CurrentRole reads ``role`` (the server looks at users.toml once a second)."""
    deadline = time.monotonic() + timeout
    while (seen := await role_of(client, env)) != role:
        assert time.monotonic() < deadline, f"the session's role is still {seen}, not {role}"
        await asyncio.sleep(0.05)


async def test_a_session_goes_on_as_anonymous_once_users_toml_no_longer_grants_its_login(env: Env) -> None:
    """Decision 99: `uacell user` (here another store on the same file, as in another process) unbinding a
    certificate, changing a password, a role, or removing a user ends the credentials of that user's open
    sessions: they go on with the anonymous role (operator on loopback, as after an expiry, decision 88),
    audited as identity_revoked; other users' sessions keep theirs."""
    badge = user_certificate("mia, badge")
    env.cli.add("mia", "engineer", "mia-password-1", certificate=badge.der)
    env.cli.add("pat", "engineer", "pat-password-1")
    env.cli.add("rae", "admin", "rae-password-1")
    mia = await cert_client(env, badge)
    pat = await secure_client(env.app, env.cert, user="pat", password="pat-password-1")
    rae = await secure_client(env.app, env.cert, user="rae", password="rae-password-1")
    try:
        assert [await role_of(c, env) for c in (mia, pat, rae)] == ["engineer", "engineer", "admin"]
        env.cli.set_password("mia", "mia-password-2")  # her certificate login does not rest on it
        env.cli.remove_certificate("mia", thumbprint(badge.der))
        await wait_for_role(mia, env, "operator")
        await audited_login_event(env, "identity_revoked", user="mia")
        assert [await role_of(c, env) for c in (pat, rae)] == ["engineer", "admin"]
        env.cli.set_password("pat", "pat-password-2")
        await wait_for_role(pat, env, "operator")
        env.cli.set_role("rae", "operator")  # not even a demotion keeps the session's admin
        await wait_for_role(rae, env, "operator")
        assert env.app.security.recheck_identities() == 0  # nothing left to take
        # the client logs in again with what the file grants now
        pat.set_password("pat-password-2")
        await pat.activate_session(username="pat", password="pat-password-2")
        assert await role_of(pat, env) == "engineer"
    finally:
        for client in (mia, pat, rae):
            await client.disconnect()
        for name in ("mia", "pat", "rae"):
            env.cli.remove(name)
