"""Security over real asyncua sessions: certificates, endpoints, trust list, logins, roles, listening policy.

Two servers per module run (setting one up takes seconds): one on loopback with the defaults, one on
0.0.0.0 (every interface, still reachable via 127.0.0.1) to show the stricter defaults.
"""

from __future__ import annotations

import logging
import time
import uuid
from pathlib import Path
from typing import cast

import pytest
import pytest_asyncio
from asyncua import Client, Server, ua
from asyncua.crypto import security_policies as sp
from conftest import fast_config, start_app
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtensionOID
from helpers import raw_call

from uacell.core.errors import CallError
from uacell.core.roles import Role
from uacell.di.companion import LOCKING
from uacell.robotics.companion import SYSTEM_OPERATION, TASK_CONTROL
from uacell.security.pki import PkiPaths, TrustList, make_client_certificate
from uacell.security.policy import prepare_certificate
from uacell.security.users import LoginThrottle
from uacell.server import APPLICATION_URI, UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

CLIENT_URI = "urn:uacell:test:client"
PASSWORD = "correct horse"
ROLES = [Role.OBSERVER, Role.OPERATOR, Role.ENGINEER, Role.ADMIN]
POLICIES = {
    "Basic256Sha256": sp.SecurityPolicyBasic256Sha256,
    "Aes128_Sha256_RsaOaep": sp.SecurityPolicyAes128Sha256RsaOaep,
    "Aes256_Sha256_RsaPss": sp.SecurityPolicyAes256Sha256RsaPss,
}
MODES = {"Sign": ua.MessageSecurityMode.Sign, "SignAndEncrypt": ua.MessageSecurityMode.SignAndEncrypt}
TC = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"


# helpers (test_locks imports these) --------------------------------------------------------------------


class ClientCert:
    """A client certificate + key on disk, made with uacell.security.pki."""

    def __init__(self, directory: Path, uri: str = CLIENT_URI) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.uri = uri
        self.der, pem = make_client_certificate(uri)
        name = uuid.uuid4().hex[:8]
        self.cert = directory / f"{name}.der"
        self.key = directory / f"{name}.pem"
        self.cert.write_bytes(self.der)
        self.key.write_bytes(pem)


async def secure_client(
    app: UacellServer,
    cert: ClientCert,
    *,
    user: str | None = None,
    password: str | None = None,
    policy: type = sp.SecurityPolicyBasic256Sha256,
    mode: ua.MessageSecurityMode = ua.MessageSecurityMode.SignAndEncrypt,
    connect: bool = True,
    endpoint: str | None = None,
) -> Client:
    client = Client(endpoint or app.endpoint, timeout=20)
    client.application_uri = cert.uri
    if user is not None:
        client.set_user(user)
        client.set_password(password or "")
    await client.set_security(policy, str(cert.cert), str(cert.key), mode=mode)
    if connect:
        await client.connect()
    return client


def default_arguments(app: UacellServer, inputs: list[ua.Argument]) -> list[ua.Variant]:
    """Well-typed, harmless input values for a method's InputArguments."""
    scalars = {
        ua.VariantType.Boolean: False,
        ua.VariantType.Float: 0.0,
        ua.VariantType.Double: 0.0,
        ua.VariantType.String: "",
        ua.VariantType.ByteString: b"",
        ua.VariantType.NodeId: ua.NodeId(0, 0),
        ua.VariantType.ExpandedNodeId: ua.ExpandedNodeId(0, 0),
        ua.VariantType.LocalizedText: ua.LocalizedText(""),
    }
    out = []
    for arg in inputs:
        vtype = app.dispatcher.types.builtin_of(arg.DataType) or ua.VariantType.Double
        if arg.ValueRank >= 0:
            out.append(ua.Variant([], vtype, is_array=True))
            continue
        out.append(ua.Variant(scalars.get(vtype, 0), vtype))
    return out


async def call(client: Client, obj: ua.NodeId, method: ua.NodeId, args: list[ua.Variant]) -> ua.CallMethodResult:
    return await raw_call(client, obj, method, *args)


# fixtures ---------------------------------------------------------------------------------------------


class SecurityServer(UacellServer):
    """``env``'s and ``wide``'s server as the tests use it: the UacellServer ``start_app`` made, with
    what the fixture attaches to it (a type for the checker: never made)."""

    test_nodes: dict[str, ua.NodeId]
    client_cert: ClientCert
    setup_log: list[logging.LogRecord]
    local_endpoint: str


async def _serve(data_dir: Path, host: str) -> UacellServer:
    config = fast_config(data_dir)
    config.server.host = host
    return await start_app(config)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory):
    """The loopback server, a trusted client certificate, users of every role, test nodes."""
    base = tmp_path_factory.mktemp("security")
    app = cast(SecurityServer, await _serve(base / "data", "127.0.0.1"))  # the test attributes follow
    cert = ClientCert(base / "client")
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(cert.der)
    for role in ROLES:
        app.users.add(f"probe-{role.label}", role, PASSWORD)
    ns = app.cell.instantiator.ns
    obj = await app.server.nodes.objects.add_object(ua.NodeId("SecurityTest", ns), ua.QualifiedName("SecurityTest", ns))
    var = await obj.add_variable(ua.NodeId("SecurityTest.Value", ns), ua.QualifiedName("Value", ns), 1.0)
    await var.set_writable()
    # A FileType's UserWritable property as the Programs files carry it (Writable is true).
    prop = await obj.add_property(ua.NodeId("SecurityTest.UserWritable", ns), ua.QualifiedName("UserWritable", 0), True)
    app.test_nodes = {"object": obj.nodeid, "value": var.nodeid, "user_writable": prop.nodeid}
    app.client_cert = cert
    try:
        yield app
    finally:
        await app.stop()


@pytest.fixture(autouse=True)
def fresh_throttle(request):
    # Every test logs in from 127.0.0.1; failures of one test must not delay the next.
    if "env" in request.fixturenames:
        request.getfixturevalue("env").security.throttle = LoginThrottle()


# certificates and endpoints ---------------------------------------------------------------------------


async def test_server_certificate_made_on_first_start_and_reused(env):
    paths = PkiPaths.in_data_dir(env.data_dir)
    der = paths.cert.read_bytes()
    cert = x509.load_der_x509_certificate(der)
    san = cast(
        x509.SubjectAlternativeName, cert.extensions.get_extension_for_oid(ExtensionOID.SUBJECT_ALTERNATIVE_NAME).value
    )
    assert APPLICATION_URI in san.get_values_for_type(x509.UniformResourceIdentifier)
    assert "127.0.0.1" in [str(i) for i in san.get_values_for_type(x509.IPAddress)]
    key = cert.public_key()
    assert isinstance(key, rsa.RSAPublicKey)  # OPC UA's RSA policies
    assert key.key_size >= 2048
    assert paths.key.stat().st_mode & 0o077 == 0
    # The endpoints carry that very certificate.
    client = Client(env.endpoint, timeout=20)
    endpoints = await client.connect_and_get_server_endpoints()
    assert {e.ServerCertificate for e in endpoints} == {der}
    # A second start with the same data directory reuses it.
    again = Server()
    path = await prepare_certificate(again, env.data_dir, APPLICATION_URI, ["127.0.0.1"])
    assert path == paths.cert and paths.cert.read_bytes() == der
    assert not paths.backup.exists()


async def test_loopback_endpoints_are_secure_policies_plus_none(env):
    client = Client(env.endpoint, timeout=20)
    endpoints = await client.connect_and_get_server_endpoints()
    offered = {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode.name) for e in endpoints}
    expected = {(p, m) for p in POLICIES for m in MODES} | {("None", "None_")}
    assert offered == expected
    none = next(e for e in endpoints if e.SecurityMode == ua.MessageSecurityMode.None_)
    token = next(t for t in none.UserIdentityTokens if t.TokenType == ua.UserTokenType.UserName)
    # On the unencrypted endpoint the password must come encrypted with the server's key.
    assert token.SecurityPolicyUri == sp.SecurityPolicyBasic256Sha256.URI
    kinds = {t.TokenType for e in endpoints for t in e.UserIdentityTokens}
    # a user certificate on every endpoint too (decision 84); no issued tokens
    assert kinds == {ua.UserTokenType.Anonymous, ua.UserTokenType.UserName, ua.UserTokenType.Certificate}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("policy", POLICIES)
async def test_secure_session_with_each_policy_and_mode(env, policy, mode):
    client = await secure_client(
        env, env.client_cert, user="probe-engineer", password=PASSWORD, policy=POLICIES[policy], mode=MODES[mode]
    )
    try:
        assert client.security_policy.URI == POLICIES[policy].URI
        assert client.security_policy.Mode == MODES[mode]
        node = client.get_node(env.test_nodes["value"])
        # the engineer's rights arrived: UserAccessLevel includes CurrentWrite
        assert (await node.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value == 3
        assert await node.read_value() == 1.0
    finally:
        await client.disconnect()


# trust list -------------------------------------------------------------------------------------------


async def test_untrusted_client_certificate_refused_with_hint(env, tmp_path, caplog):
    stranger = ClientCert(tmp_path, "urn:uacell:test:stranger")
    caplog.set_level(logging.INFO, logger="uacell.security.policy")
    with pytest.raises(ua.UaStatusCodeError) as err:
        await secure_client(env, stranger)
    assert err.value.code == ua.StatusCodes.BadCertificateUntrusted
    paths = PkiPaths.in_data_dir(env.data_dir)
    rejected = [p for p in paths.rejected.iterdir() if p.read_bytes() == stranger.der]
    assert len(rejected) == 1
    lines = [r.getMessage() for r in caplog.records if "refused untrusted client certificate" in r.getMessage()]
    assert lines and str(rejected[0]) in lines[-1] and str(paths.trusted) in lines[-1]
    # Moving the file to trusted/ is enough; no restart.
    rejected[0].rename(paths.trusted / rejected[0].name)
    client = await secure_client(env, stranger)
    await client.disconnect()


async def test_trust_on_first_use_keeps_the_certificate(env, tmp_path):
    newcomer = ClientCert(tmp_path, "urn:uacell:test:newcomer")
    trust_list = env.security.trust_list
    trust_list.trust_on_first_use = True
    try:
        client = await secure_client(env, newcomer)
        await client.disconnect()
    finally:
        trust_list.trust_on_first_use = False
    assert trust_list.is_trusted(newcomer.der)


# logins -----------------------------------------------------------------------------------------------


async def test_wrong_password_refused_at_activate_session(env):
    with pytest.raises(ua.UaStatusCodeError) as err:
        await secure_client(env, env.client_cert, user="probe-operator", password="wrong")
    assert err.value.code == ua.StatusCodes.BadUserAccessDenied
    with pytest.raises(ua.UaStatusCodeError) as err:
        await secure_client(env, env.client_cert, user="nobody", password=PASSWORD)
    assert err.value.code == ua.StatusCodes.BadUserAccessDenied


async def test_clear_text_password_on_unencrypted_channel_refused(env):
    client = Client(env.endpoint, timeout=20)
    client.set_user("probe-engineer")
    client.set_password(PASSWORD)
    original = client.server_policy

    def plaintext_policy(token_type):
        policy = original(token_type)
        return ua.UserTokenPolicy(
            PolicyId=policy.PolicyId, TokenType=policy.TokenType, SecurityPolicyUri=sp.SecurityPolicyNone.URI
        )

    client.server_policy = plaintext_policy
    with pytest.raises(ua.UaStatusCodeError) as err:
        await client.connect()
    assert err.value.code == ua.StatusCodes.BadIdentityTokenRejected


async def test_encrypted_password_token_accepted_on_none_channel(env):
    client = Client(env.endpoint, timeout=20)
    client.set_user("probe-engineer")
    client.set_password(PASSWORD)
    await client.connect()  # asyncua encrypts the token as the endpoint asks
    try:
        node = client.get_node(env.test_nodes["value"])
        assert (await node.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value == 3
    finally:
        await client.disconnect()


async def test_repeated_failures_are_slowed_down(env):
    env.security.throttle = LoginThrottle(base=1.0, cap=2.0, free=1)
    client = await secure_client(env, env.client_cert, connect=False)
    # One session, several ActivateSession attempts: only the login itself is timed.
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()
    await client.create_session()

    async def attempt(password: str) -> tuple[float, bool]:
        start = time.monotonic()
        try:
            await client.activate_session("probe-operator", password)
        except ua.UaStatusCodeError as exc:
            assert exc.code == ua.StatusCodes.BadUserAccessDenied
            return time.monotonic() - start, False
        return time.monotonic() - start, True

    try:
        _, ok1 = await attempt("wrong")
        _, ok2 = await attempt("wrong")  # undelayed; after this one the delays start
        third, ok3 = await attempt("wrong")
        fourth, ok4 = await attempt(PASSWORD)
        assert (ok1, ok2, ok3, ok4) == (False, False, False, True)
        # A delay is a lower bound whatever the machine's load; the undelayed attempts are not timed.
        assert third >= 1.0  # waited 1 s
        assert fourth >= 2.0  # waited 2 s, the doubled delay, even with the right password
        after, ok5 = await attempt("wrong")  # the success reset the count: no 2 s wait again
        assert not ok5 and after < fourth
    finally:
        await client.close_session()
        await client.close_secure_channel()
        client.disconnect_socket()


# rights ---------------------------------------------------------------------------------------------


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def sessions(env):
    """One user-name session per role."""
    clients = {}
    for role in ROLES:
        clients[role] = await secure_client(env, env.client_cert, user=f"probe-{role.label}", password=PASSWORD)
    try:
        yield clients
    finally:
        for c in clients.values():
            await c.disconnect()


async def test_user_attributes_differ_per_role(env, sessions):
    for role, client in sessions.items():
        value = client.get_node(env.test_nodes["value"])
        ual = (await value.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value
        assert ual == (3 if role >= Role.ENGINEER else 1), role
        assert (await value.read_attribute(ua.AttributeIds.AccessLevel)).Value.Value == 3
        writable = await client.get_node(env.test_nodes["user_writable"]).read_value()
        assert writable is (role >= Role.ENGINEER), role


async def test_each_session_reads_its_own_role_in_server_current_role(env, sessions):
    """uacell's Server/CurrentRole (decision 39): one node, each session reads the role it has."""
    for role, client in sessions.items():
        server = client.get_node(ua.NodeId(ua.ObjectIds.Server))
        node = await server.get_child(f"{await client.get_namespace_index('urn:uacell:cell')}:CurrentRole")
        assert await node.read_value() == role.label, role
        assert (await node.read_data_type_as_variant_type()) == ua.VariantType.String
    anonymous = await secure_client(env, env.client_cert)
    try:
        ns = await anonymous.get_namespace_index("urn:uacell:cell")
        node = anonymous.get_node(ua.NodeId("Server.CurrentRole", ns))
        assert await node.read_value() == "operator"  # the anonymous role on a loopback-only server
        assert await anonymous.get_node(ua.NodeId("Server.CurrentUser", ns)).read_value() == ""
    finally:
        await anonymous.disconnect()


async def test_each_session_reads_its_own_user_in_server_current_user(env, sessions):
    """uacell's Server/CurrentUser (decision 103): one node, each session reads the user it is logged in as."""
    for role, client in sessions.items():
        server = client.get_node(ua.NodeId(ua.ObjectIds.Server))
        node = await server.get_child(f"{await client.get_namespace_index('urn:uacell:cell')}:CurrentUser")
        assert await node.read_value() == f"probe-{role.label}", role
        assert (await node.read_data_type_as_variant_type()) == ua.VariantType.String


async def test_writes_checked_against_the_role_table(env, sessions):
    node_id = env.test_nodes["value"]
    for role, client in sessions.items():
        params = ua.WriteParameters()
        wv = ua.WriteValue(
            NodeId=node_id,
            AttributeId=ua.AttributeIds.Value,
            Value=ua.DataValue(ua.Variant(float(role) + 10, ua.VariantType.Double)),
        )
        params.NodesToWrite = [wv]
        (status,) = await client.uaclient.write(params)
        if role >= Role.ENGINEER:
            assert status.is_good(), role
            assert await client.get_node(node_id).read_value() == float(role) + 10
        else:
            assert status.value == ua.StatusCodes.BadUserAccessDenied, role
            assert await client.get_node(node_id).read_value() != float(role) + 10


async def test_role_method_matrix(env, sessions):
    """Every bound method, every role: Bad_UserAccessDenied exactly where the role table says so.

    A probe guard (after the role check, before the behaviour) answers allowed calls with
    Bad_InvalidState, so nothing moves.
    """

    def probe(caller, bound):
        if (caller.user or "").startswith("probe-"):
            raise CallError("BadInvalidState", "probe")

    env.dispatcher.guards.insert(0, probe)
    may_call = env.dispatcher.roles.may_call
    checked = 0
    families = set()
    try:
        for bound in list(env.dispatcher.methods.values()):
            args = default_arguments(env, bound.inputs)
            mode = args[bound.file_mode_argument].Value if bound.file_mode_argument is not None else None
            for role, client in sessions.items():
                res = await call(client, bound.object_id, bound.method_id, args)
                allowed = may_call(role, bound.name, bound.family, file_mode=mode)
                want = ua.StatusCodes.BadInvalidState if allowed else ua.StatusCodes.BadUserAccessDenied
                assert res.StatusCode.value == want, (bound.family, bound.name, role, res.StatusCode.name)
                executable = (
                    await client.get_node(bound.method_id).read_attribute(ua.AttributeIds.Executable)
                ).Value.Value
                user_exec = (
                    await client.get_node(bound.method_id).read_attribute(ua.AttributeIds.UserExecutable)
                ).Value.Value
                assert user_exec is (executable and may_call(role, bound.name, bound.family)), (
                    bound.name,
                    role,
                )
                checked += 1
            families.add(bound.family)
    finally:
        env.dispatcher.guards.remove(probe)
    # The matrix covered what is bound today, at least Robotics and locks.
    assert {TASK_CONTROL, SYSTEM_OPERATION, LOCKING} <= families
    assert checked == 4 * len(env.dispatcher.methods)


# listening policy on every interface ----------------------------------------------------------------


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def wide(tmp_path_factory):
    """A server listening on 0.0.0.0 (all interfaces), reached through 127.0.0.1."""
    base = tmp_path_factory.mktemp("wide")
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign, assignment]  # a list collects the records
    logging.getLogger("uacell").addHandler(handler)
    try:
        app = cast(SecurityServer, await _serve(base / "data", "0.0.0.0"))  # the test attributes follow
    finally:
        logging.getLogger("uacell").removeHandler(handler)
    app.setup_log = records
    app.client_cert = ClientCert(base / "client")
    TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(app.client_cert.der)
    app.local_endpoint = f"opc.tcp://127.0.0.1:{app.config.server.port}/"
    try:
        yield app
    finally:
        await app.stop()


async def test_non_loopback_offers_no_none_endpoint(wide):
    assert wide.policy.none_security is False and wide.policy.anonymous_role == Role.OBSERVER
    client = Client(wide.local_endpoint, timeout=20)
    endpoints = await client.connect_and_get_server_endpoints()
    assert endpoints and all(e.SecurityMode != ua.MessageSecurityMode.None_ for e in endpoints)
    assert {e.SecurityPolicyUri.rsplit("#", 1)[1] for e in endpoints} == set(POLICIES)
    plain = Client(wide.local_endpoint, timeout=10)
    with pytest.raises(Exception):  # noqa: B017 - refused while opening the channel; the code varies
        await plain.connect()
    # the defaults are not loosened, so nothing to warn about
    assert not [r for r in wide.setup_log if "configuration" in r.getMessage()]


async def test_non_loopback_anonymous_is_observer(wide):
    client = await secure_client(wide, wide.client_cert, endpoint=wide.local_endpoint)
    try:
        ns = await client.get_namespace_index("urn:uacell:cell")
        tc = ua.NodeId(TC, ns)
        method = ua.NodeId(f"{TC}.LoadByName", ns)
        res = await call(client, tc, method, [ua.Variant("x", ua.VariantType.String)])
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
        assert (await client.get_node(method).read_attribute(ua.AttributeIds.UserExecutable)).Value.Value is False
        lock = ua.NodeId("Robot1.Controllers.Controller1.Lock", ns)
        res = await call(
            client,
            lock,
            ua.NodeId("Robot1.Controllers.Controller1.Lock.InitLock", ns),
            [ua.Variant("", ua.VariantType.String)],
        )
        assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
        # reading stays open
        assert (await client.get_node(ua.NodeId(f"{TC}.CurrentState", ns)).read_value()).Text == "Idle"
    finally:
        await client.disconnect()
