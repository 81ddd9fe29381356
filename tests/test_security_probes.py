"""Probes with hand-built OPC UA messages (tests/uaraw.py), as an attacker on the plant network sends them:
a SecurityPolicy None channel where None is not offered, policies and modes no endpoint has, replayed
and mis-encrypted user tokens, a flood of untrusted certificates.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import socket
import subprocess
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import cast

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto import security_policies as sp
from conftest import fast_config, start_app, start_serve
from cryptography import x509
from uaraw import Fault, RawClient, Refused, anonymous_token, none_session, user_token

from uacell.security.pki import PkiPaths, TrustList, generate_key, make_certificate, make_client_certificate, thumbprint
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

PASSWORD = "probe password"
CLIENT_URI = "urn:uacell:test:probe"
RSA15 = "http://www.w3.org/2001/04/xmlenc#rsa-1_5"
OAEP = "http://www.w3.org/2001/04/xmlenc#rsa-oaep"
OAEP256 = "http://opcfoundation.org/UA/security/rsa-oaep-sha2-256"
REJECTED_CAP = 5
NONE_URI = sp.SecurityPolicyNone.URI
S = ua.StatusCodes


def _server_certificate(app: UacellServer) -> x509.Certificate:
    return x509.load_der_x509_certificate(PkiPaths.in_data_dir(app.data_dir).cert.read_bytes())


def _secure_policy(app: UacellServer, mode: ua.MessageSecurityMode, key=None, uri: str = CLIENT_URI):
    """A client-side Basic256Sha256 policy with a fresh self-signed certificate (same key when given)."""
    key = key or generate_key()
    cert = make_certificate(key, uri, common_name=f"probe {uuid.uuid4().hex[:8]}", server=False)
    policy = sp.SecurityPolicyBasic256Sha256(_server_certificate(app), cert, key, mode)
    return policy, cert


class _UnofferedPolicy(sp.SecurityPolicyNone):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
    """Frames like policy None but names a policy the server does not offer in its header."""

    URI = "http://opcfoundation.org/UA/SecurityPolicy#Basic128Rsa15"


async def _get_endpoints(raw: RawClient) -> list[ua.EndpointDescription]:
    request = ua.GetEndpointsRequest()
    request.Parameters.EndpointUrl = raw.url
    return (await raw.request(request, ua.GetEndpointsResponse)).Endpoints


def _warnings(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    """The refusals logged with ``text``: INFO lines (a client's doing), never a traceback."""
    found = [r for r in caplog.records if r.levelno >= logging.INFO and text in r.getMessage()]
    assert not [r for r in found if r.exc_info or r.levelno >= logging.ERROR]
    return [r.getMessage() for r in found]


# fixtures ---------------------------------------------------------------------------------------------


class ProbedServer(UacellServer):
    """``env``'s server as the tests use it: the UacellServer ``start_app`` made, with the trusted
    client's certificate and key files attached by the fixture (a type for the checker: never made)."""

    client_files: tuple[Path, Path]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory):
    """A loopback server (None offered) with an engineer, a trusted client and a small rejected/ cap."""
    config = fast_config(tmp_path_factory.mktemp("probes") / "data")
    config.server.rejected_max_files = REJECTED_CAP
    app = cast(ProbedServer, await start_app(config))  # client_files is attached below
    app.users.add("eve-engineer", "engineer", PASSWORD)
    ns = app.cell.instantiator.ns
    var = await app.server.nodes.objects.add_variable(ua.NodeId("ProbeTest.Value", ns), "ProbeTest", 1.0)
    await var.set_writable()
    der, pem = make_client_certificate(CLIENT_URI)
    client_dir = tmp_path_factory.mktemp("probe-client")
    (client_dir / "cert.der").write_bytes(der)
    (client_dir / "key.pem").write_bytes(pem)
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(der)
    app.client_files = (client_dir / "cert.der", client_dir / "key.pem")
    try:
        yield app
    finally:
        await app.stop()


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def wide(tmp_path_factory):
    """A server listening on 0.0.0.0 (so None is not offered), probed through 127.0.0.1."""
    config = fast_config(tmp_path_factory.mktemp("probes-wide") / "data")
    config.server.host = "0.0.0.0"
    with socket.socket() as s:  # a port free on every interface
        s.bind(("0.0.0.0", 0))
        config.server.port = s.getsockname()[1]
    app = await start_app(config)
    try:
        yield app
    finally:
        await app.stop()


@pytest.fixture(autouse=True)
def fresh_refusal_log(request):
    # Refusals are logged once per address and interval; each test looks at its own.
    for name in ("env", "wide"):
        if name in request.fixturenames:
            from uacell.core.logs import RefusalLog

            request.getfixturevalue(name).security.refusals = RefusalLog()


# 1. policy None where it is not offered -----------------------------------------------------------------


async def test_none_channel_on_every_interface_serves_discovery_only(wide, caplog):
    port = wide.config.server.port
    caplog.set_level(logging.INFO, logger="uacell.security.policy")
    for attempt in range(2):
        async with await RawClient.connect("127.0.0.1", port) as raw:
            await raw.hello()
            await raw.open_channel()  # policy None: kept for discovery
            endpoints = await _get_endpoints(raw)
            assert endpoints and {e.SecurityPolicyUri for e in endpoints}.isdisjoint({NONE_URI})
            with pytest.raises(Fault) as refused:
                await raw.create_session()
            assert refused.value.code == S.BadSecurityPolicyRejected
            # Nor can a None channel take over or use a session: every other request is refused too.
            raw.auth = ua.NodeId(1000 + attempt)
            with pytest.raises(Fault) as refused:
                await raw.activate_session(anonymous_token())
            assert refused.value.code == S.BadSecurityPolicyRejected
            with pytest.raises(Fault) as refused:
                await raw.read_value(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
            assert refused.value.code == S.BadSecurityPolicyRejected
    # Six refusals from one address: logged once in the interval, and asyncua does not echo each one.
    assert len(_warnings(caplog, "refused request from 127.0.0.1")) == 1
    assert not [r for r in caplog.records if r.name.startswith("asyncua")]


async def test_channel_policy_or_mode_not_offered_is_refused(wide):
    port = wide.config.server.port
    policy, _ = _secure_policy(wide, ua.MessageSecurityMode.Sign)
    cases = [
        (_UnofferedPolicy(), None, S.BadSecurityPolicyRejected),  # a policy no endpoint has
        (sp.SecurityPolicyNone(), ua.MessageSecurityMode.Sign, S.BadSecurityModeRejected),
        (policy, ua.MessageSecurityMode.None_, S.BadSecurityModeRejected),  # Basic256Sha256 without security
    ]
    for client_policy, mode, code in cases:
        async with await RawClient.connect("127.0.0.1", port, policy=client_policy) as raw:
            await raw.hello()
            with pytest.raises(Refused) as refused:
                await raw.open_channel(mode=mode)
            assert refused.value.code == code, client_policy.URI
            assert await raw.at_eof()


async def test_create_session_wants_an_opc_tcp_endpoint_url(env):
    async with await RawClient.connect("127.0.0.1", env.config.server.port) as raw:
        await raw.hello()
        await raw.open_channel()
        with pytest.raises(Fault) as refused:
            await raw.create_session(endpoint_url=f"http://127.0.0.1:{env.config.server.port}/")
        assert refused.value.code == S.BadTcpEndpointUrlInvalid
        with pytest.raises(Fault) as refused:  # the refused session cannot be activated afterwards
            await raw.activate_session(anonymous_token())
        assert refused.value.code == S.BadSessionIdInvalid
        await raw.create_session()  # with the URL it used
        await raw.activate_session(anonymous_token())


# a plant-network address in a network namespace --------------------------------------------------------

PLANT_ADDRESS = "192.0.2.10"  # TEST-NET-1
CLONE_NEWNET = 0x40000000


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=False)


@pytest.fixture
def plant_namespace() -> Iterator[str]:
    """A network namespace whose loopback also carries PLANT_ADDRESS; removed afterwards."""
    name = f"uacell-probe-{uuid.uuid4().hex[:8]}"
    try:
        made = _ip("netns", "add", name)
    except FileNotFoundError:
        pytest.skip("cannot create a network namespace: the ip command (iproute2) is missing")
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace (needs root and iproute2): {made.stderr.strip()}")
    try:
        for args in (("link", "set", "lo", "up"), ("addr", "add", f"{PLANT_ADDRESS}/32", "dev", "lo")):
            result = _ip("-n", name, *args)
            assert result.returncode == 0, result.stderr
        yield name
    finally:
        _ip("netns", "delete", name)


def _connect_in_namespace(namespace: str, host: str, port: int) -> socket.socket:
    """A TCP connection made from inside ``namespace`` (by a thread that joins it), non-blocking."""
    result: dict[str, object] = {}

    def run() -> None:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            with open(f"/run/netns/{namespace}") as ns:
                if libc.setns(ns.fileno(), CLONE_NEWNET) != 0:
                    raise OSError(ctypes.get_errno(), "setns failed")
            sock = socket.create_connection((host, port), timeout=30)
            sock.setblocking(False)
            result["sock"] = sock
        except BaseException as exc:
            result["error"] = exc

    thread = threading.Thread(target=run)  # the thread ends inside the namespace; the process does not
    thread.start()
    thread.join()
    if "error" in result:
        raise result["error"]  # type: ignore[misc]
    return result["sock"]  # type: ignore[return-value]


@contextlib.contextmanager
def _serve_in_namespace(namespace: str, data_dir: Path, port: int) -> Iterator[None]:
    served = start_serve(data_dir, port=port, host=PLANT_ADDRESS, prefix=("ip", "netns", "exec", namespace))
    try:
        yield
    finally:
        served.stop()


async def test_none_channel_on_a_plant_network_address(plant_namespace, tmp_path):
    port = 4840  # the namespace is empty: the standard port is free there
    with _serve_in_namespace(plant_namespace, tmp_path / "data", port):
        sock = _connect_in_namespace(plant_namespace, PLANT_ADDRESS, port)
        async with await RawClient.connect(PLANT_ADDRESS, port, sock=sock) as raw:
            await raw.hello()
            await raw.open_channel()
            endpoints = await _get_endpoints(raw)
            assert endpoints and all(e.SecurityMode != ua.MessageSecurityMode.None_ for e in endpoints)
            with pytest.raises(Fault) as refused:
                await raw.create_session()
            assert refused.value.code == S.BadSecurityPolicyRejected
            with pytest.raises(Fault) as refused:
                await raw.activate_session(anonymous_token())
            assert refused.value.code == S.BadSecurityPolicyRejected


# 2./3. user tokens --------------------------------------------------------------------------------------


async def _capture_engineer_token(app: ProbedServer) -> ua.UserNameIdentityToken:
    """An engineer logs in on a Basic256Sha256 Sign channel; the sniffed (encrypted) token is returned."""
    cert, key = app.client_files
    client = Client(app.endpoint, timeout=30)
    client.application_uri = CLIENT_URI
    client.set_user("eve-engineer")
    client.set_password(PASSWORD)
    await client.set_security(sp.SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.Sign)
    captured: list[ua.UserNameIdentityToken] = []
    original = client.uaclient.activate_session

    async def sniff(params: ua.ActivateSessionParameters):
        captured.append(params.UserIdentityToken)
        return await original(params)

    client.uaclient.activate_session = sniff
    await client.connect()
    await client.disconnect()
    (token,) = captured
    assert token.EncryptionAlgorithm == OAEP and token.Password
    return token


async def _engineer_may_write(raw: RawClient) -> bool:
    """UserAccessLevel of a variable operators may not write: CurrentWrite only for engineers."""
    ns = await raw.namespace_index("urn:uacell:cell")
    node = ua.NodeId("ProbeTest.Value", ns)
    request = ua.ReadRequest()
    request.Parameters.NodesToRead = [ua.ReadValueId(NodeId=node, AttributeId=ua.AttributeIds.UserAccessLevel)]
    (dv,) = (await raw.request(request, ua.ReadResponse)).Results
    return bool(dv.Value.Value & ua.AccessLevel.CurrentWrite.mask)


async def test_replayed_user_token_is_refused(env):
    sniffed = await _capture_engineer_token(env)
    raw, session = await none_session("127.0.0.1", env.config.server.port)
    async with raw:
        with pytest.raises(Fault) as refused:
            await raw.activate_session(sniffed)
        assert refused.value.code == S.BadIdentityTokenInvalid
        with pytest.raises(Fault) as refused:  # the session stays unactivated
            await raw.read_value(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
        assert refused.value.code in (S.BadSessionNotActivated, S.BadUserAccessDenied)  # asyncua says the latter
        # The same login with this session's nonce works: only the nonce made the difference.
        fresh = user_token("eve-engineer", PASSWORD, session.nonce, session.server_certificate)
        result = await raw.activate_session(fresh)
        assert await _engineer_may_write(raw)
        assert result.ServerNonce and result.ServerNonce != session.nonce
        # A nonce is never accepted twice: the same token again in the same session is refused.
        with pytest.raises(Fault) as refused:
            await raw.activate_session(fresh)
        assert refused.value.code == S.BadIdentityTokenInvalid


async def test_user_token_encrypted_with_another_algorithm_is_refused(env):
    raw, session = await none_session("127.0.0.1", env.config.server.port)
    async with raw:
        nonce, cert = session.nonce, session.server_certificate
        # The None endpoint's user-name policy is Basic256Sha256: RSA-OAEP (SHA-1).
        for algorithm in (RSA15, OAEP256):
            with pytest.raises(Fault) as refused:
                await raw.activate_session(user_token("eve-engineer", PASSWORD, nonce, cert, algorithm=algorithm))
            assert refused.value.code == S.BadIdentityTokenInvalid, algorithm
        with pytest.raises(Fault) as refused:  # a user token policy the endpoint does not have
            await raw.activate_session(user_token("eve-engineer", PASSWORD, nonce, cert, policy_id="bogus"))
        assert refused.value.code == S.BadIdentityTokenInvalid
        await raw.activate_session(user_token("eve-engineer", PASSWORD, nonce, cert, algorithm=OAEP))
        assert await _engineer_may_write(raw)


# sessions moved to another secure channel (OPC 10000-4, 5.6.3.1) ----------------------------------------


async def test_session_cannot_be_taken_over_from_another_channel(env):
    port = env.config.server.port
    cert, key = env.client_files
    victim = Client(env.endpoint, timeout=30)
    victim.application_uri = CLIENT_URI
    await victim.set_security(sp.SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.Sign)
    await victim.connect()
    try:
        stolen = victim.uaclient.protocol.authentication_token
        assert stolen.NodeIdType == ua.NodeIdType.ByteString and len(stolen.Identifier) == 32  # not guessable
        async with await RawClient.connect("127.0.0.1", port) as thief:
            await thief.hello()
            await thief.open_channel()  # None: no certificate, unlike the victim's channel
            thief.auth = stolen
            with pytest.raises(Fault) as refused:
                await thief.activate_session(anonymous_token())
            assert refused.value.code == S.BadSecurityChecksFailed
        state = victim.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
        assert await state.read_value() == ua.ServerState.Running  # the victim keeps its session
    finally:
        await victim.disconnect()


async def test_session_moves_to_a_new_channel_only_activated_and_with_the_same_identity(env):
    port = env.config.server.port
    first, fresh = await none_session("127.0.0.1", port)
    async with first:
        async with await RawClient.connect("127.0.0.1", port) as second:
            await second.hello()
            await second.open_channel()
            second.auth = first.auth
            with pytest.raises(Fault) as refused:  # first activation belongs to the creating channel
                await second.activate_session(anonymous_token())
            assert refused.value.code == S.BadSessionNotActivated
        result = await first.activate_session(anonymous_token())
        async with await RawClient.connect("127.0.0.1", port) as third:
            await third.hello()
            await third.open_channel()
            third.auth = first.auth
            token = user_token("eve-engineer", PASSWORD, result.ServerNonce, fresh.server_certificate)
            with pytest.raises(Fault) as refused:
                await third.activate_session(token)
            assert refused.value.code == S.BadIdentityChangeNotSupported
            await third.activate_session(anonymous_token())  # the same identity, same (no) certificate
            state = await third.read_value(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
            assert state.Value.Value == ua.ServerState.Running


# 5. a flood of untrusted certificates -----------------------------------------------------------------


async def test_flood_of_untrusted_certificates_keeps_rejected_capped(env, caplog):
    caplog.set_level(logging.INFO, logger="uacell")
    rejected = PkiPaths.in_data_dir(env.data_dir).rejected
    key = generate_key()  # one key, a fresh self-signed certificate per attempt (as a flood would)
    thumbprints = []
    for _ in range(REJECTED_CAP + 7):
        policy, _ = _secure_policy(env, ua.MessageSecurityMode.Sign, key=key)
        der = policy.host_certificate
        thumbprints.append(thumbprint(der))
        async with await RawClient.connect("127.0.0.1", env.config.server.port, policy=policy) as raw:
            await raw.hello()
            await raw.open_channel()
            with pytest.raises(Fault) as refused:
                await raw.create_session(certificate=der, application_uri=CLIENT_URI)
            assert refused.value.code == S.BadCertificateUntrusted
    kept = sorted(p.name for p in rejected.iterdir())
    assert len(kept) == REJECTED_CAP
    assert {f"{t}.der" for t in thumbprints[-REJECTED_CAP:]} == set(kept)  # named by thumbprint
    assert len(_warnings(caplog, "keeps at most")) == 1  # logged once, not per dropped file
    assert len(_warnings(caplog, "refused untrusted client certificate")) == 1  # once per address and minute
    assert os.listdir(PkiPaths.in_data_dir(env.data_dir).trusted)  # the trusted client is untouched
