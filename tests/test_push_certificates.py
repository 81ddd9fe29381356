"""ServerConfiguration's push model (OPC 10000-12 7.10, decision 96) through a real asyncua client over
TCP, as a GDS uses it: a signing request for a new key, the certificate a CA issued for it (tests/plant_ca.py,
from RFC 2986/5280), UpdateCertificate and ApplyChanges, then what new clients are sent; each refusal with
the standard's code and nothing changed."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from helpers import secure_client
from plant_ca import Authority, application_certificate, der, key_pem, parse_trust_list, trust_list_bytes

from uacell.core.roles import Role
from uacell.security.pki import PkiPaths, TrustList
from uacell.server import UacellServer
from uacell.web.hosting import hmi_certificate
from uacell.web.uasession import Credentials, UaSession

pytestmark = pytest.mark.asyncio(loop_scope="module")

OBJ = ua.ObjectIds
CONFIGURATION = ua.NodeId(OBJ.ServerConfiguration)
GROUP = ua.NodeId(OBJ.ServerConfiguration_CertificateGroups_DefaultApplicationGroup)
RSA_SHA256 = ua.NodeId(OBJ.RsaSha256ApplicationCertificateType)
PASSWORD = "push-certificates-pw-1"
GDS = "urn:plant:gds"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def plant(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[dict[str, Any]]:
    """The server, trusting the plant's root; its admin and operator; the CA and the GDS's certificate."""
    root = Authority.root()
    issuing = root.intermediate()
    gds_cert, gds_key = issuing.application(GDS, "Plant GDS")
    app = await start_app(fast_config(tmp_path_factory.mktemp("push") / "data"))
    paths = PkiPaths.in_data_dir(app.data_dir)
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    (paths.crl / "root.crl").write_bytes(root.crl())
    (paths.crl / "issuing.crl").write_bytes(issuing.crl())
    app.users.add("ada", Role.ADMIN, PASSWORD)
    app.users.add("otto", Role.OPERATOR, PASSWORD)
    try:
        yield {"app": app, "paths": paths, "root": root, "issuing": issuing, "gds": (gds_cert, gds_key)}
    finally:
        await app.stop()


async def gds_session(plant: dict[str, Any], tmp_path: Path, user: str = "ada", mode: Any = None) -> Client:
    client = await secure_client(plant["app"].endpoint, tmp_path, plant["gds"][0], plant["gds"][1], GDS)
    if mode is not None:  # the same certificate over another mode
        await client.set_security(
            type(client.security_policy),
            str(tmp_path / "c.der"),
            str(tmp_path / "k.pem"),
            mode=mode,
        )
    client.set_user(user)
    client.set_password(PASSWORD)
    await client.connect()
    return client


async def call(client: Client, method: int, *args: ua.Variant) -> ua.CallMethodResult:
    request = ua.CallMethodRequest()
    request.ObjectId = CONFIGURATION
    request.MethodId = ua.NodeId(method)
    request.InputArguments = list(args)
    [result] = await client.uaclient.call([request])
    return result


def csr_args(subject: str = "", new_key: bool = False, nonce: bytes = b"") -> list[ua.Variant]:
    return [
        ua.Variant(GROUP, ua.VariantType.NodeId),
        ua.Variant(RSA_SHA256, ua.VariantType.NodeId),
        ua.Variant(subject, ua.VariantType.String),
        ua.Variant(new_key, ua.VariantType.Boolean),
        ua.Variant(nonce, ua.VariantType.ByteString),
    ]


def update_args(certificate: bytes, issuers: list[bytes], key_format: str = "", key: bytes = b"") -> list[ua.Variant]:
    return [
        ua.Variant(GROUP, ua.VariantType.NodeId),
        ua.Variant(RSA_SHA256, ua.VariantType.NodeId),
        ua.Variant(certificate, ua.VariantType.ByteString),
        ua.Variant(issuers, ua.VariantType.ByteString, is_array=True),
        ua.Variant(key_format, ua.VariantType.String),
        ua.Variant(key, ua.VariantType.ByteString),
    ]


async def hmi_reaches(app: UacellServer, server_certificate: Any) -> bool:
    """Does the web HMI's OPC UA client, trusting ``server_certificate``, get a session and read?"""
    cert, key = hmi_certificate(app.data_dir)
    trusted = TrustList(PkiPaths.in_data_dir(app.data_dir)).trust(cert.read_bytes())
    client = await UaSession(app.endpoint, Credentials(cert, key, server_certificate))._new_client()
    client.session_timeout = 10000
    client.secure_channel_timeout = 10000
    try:
        await asyncio.wait_for(client.connect(), 10)
        return bool(await client.nodes.server_state.read_value() == ua.ServerState.Running)
    except (ua.UaError, OSError, TimeoutError):
        return False
    finally:
        with contextlib.suppress(Exception):
            await client.disconnect()
        trusted.unlink()  # the other tests' trust list is the plant's alone


async def endpoint_certificates(app: UacellServer) -> set[bytes]:
    return {e.ServerCertificate for e in await Client(app.endpoint, timeout=20).connect_and_get_server_endpoints()}


async def test_a_gds_pushes_a_certificate_of_the_plant_ca(plant: dict[str, Any], tmp_path: Path) -> None:
    app, paths, issuing = plant["app"], plant["paths"], plant["issuing"]
    old = paths.cert.read_bytes()
    client = await gds_session(plant, tmp_path)
    try:
        types = await client.get_node(
            ua.NodeId(OBJ.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_CertificateTypes)
        ).read_value()
        assert types == [RSA_SHA256]
        formats = await client.get_node(ua.NodeId(OBJ.ServerConfiguration_SupportedPrivateKeyFormats)).read_value()
        assert formats == ["PEM"]
        result = await call(
            client,
            OBJ.ServerConfiguration_CreateSigningRequest,
            *csr_args("CN=Line 3 uacell/O=Plant", True, os.urandom(32)),
        )
        assert result.StatusCode.is_good(), result.StatusCode
        request = x509.load_der_x509_csr(result.OutputArguments[0].Value)
        assert request.is_signature_valid
        assert request.subject.rfc4514_string() == "O=Plant,CN=Line 3 uacell"
        san = request.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.UniformResourceIdentifier) == [app.config.server.application_uri]
        assert paths.pending_key.exists() and paths.cert.read_bytes() == old  # the server's key is unchanged
        issued = issuing.sign_request(request.public_bytes(serialization.Encoding.PEM))
        result = await call(client, OBJ.ServerConfiguration_UpdateCertificate, *update_args(der(issued), [issuing.der]))
        assert result.StatusCode.is_good(), result.StatusCode
        assert result.OutputArguments[0].Value is True  # ApplyChangesRequired
        assert paths.cert.read_bytes() == der(issued) and not paths.pending_key.exists()
        assert await endpoint_certificates(app) == {old}  # not yet
        # the web HMI beside the server trusts what the server sends, not the file (`uacell serve`)
        assert app.served_certificate() == old
        assert await hmi_reaches(app, app.served_certificate)
        assert not await hmi_reaches(app, paths.cert)  # the file's certificate is not the one sent yet
        result = await call(client, OBJ.ServerConfiguration_ApplyChanges)
        assert result.StatusCode.is_good(), result.StatusCode
        assert await endpoint_certificates(app) == {der(issued) + issuing.der}
        assert app.served_certificate() == der(issued)
        assert await hmi_reaches(app, app.served_certificate)
        # the GDS's own session goes on over the channel it opened
        assert await client.nodes.server_state.read_value() == ua.ServerState.Running
    finally:
        await client.disconnect()
    # a new client gets a channel and a session with the new certificate
    again = await gds_session(plant, tmp_path)
    try:
        assert again.security_policy.peer_certificate == der(issued)
        assert await again.nodes.server_state.read_value() == ua.ServerState.Running
    finally:
        await again.disconnect()


async def test_what_a_gds_may_not_do_is_refused_and_changes_nothing(plant: dict[str, Any], tmp_path: Path) -> None:
    paths, issuing = plant["paths"], plant["issuing"]
    before = paths.cert.read_bytes()
    operator = await gds_session(plant, tmp_path, "otto")
    try:
        result = await call(operator, OBJ.ServerConfiguration_CreateSigningRequest, *csr_args())
        assert result.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await operator.disconnect()
    signed_only = await gds_session(plant, tmp_path, mode=ua.MessageSecurityMode.Sign)
    try:
        result = await call(signed_only, OBJ.ServerConfiguration_GetRejectedList)
        assert result.StatusCode.value == ua.StatusCodes.BadSecurityModeInsufficient
    finally:
        await signed_only.disconnect()
    admin = await gds_session(plant, tmp_path)
    try:
        refusals: list[tuple[int, list[ua.Variant], int]] = [
            (
                OBJ.ServerConfiguration_CreateSigningRequest,
                csr_args(new_key=True, nonce=b"short"),
                ua.StatusCodes.BadInvalidArgument,
            ),
            (
                OBJ.ServerConfiguration_CreateSigningRequest,
                csr_args("no name at all"),
                ua.StatusCodes.BadInvalidArgument,
            ),
            (
                OBJ.ServerConfiguration_CreateSigningRequest,
                [ua.Variant(ua.NodeId(1, 5), ua.VariantType.NodeId), *csr_args()[1:]],
                ua.StatusCodes.BadInvalidArgument,
            ),
            (OBJ.ServerConfiguration_UpdateCertificate, update_args(b"junk", []), ua.StatusCodes.BadCertificateInvalid),
            # another key's certificate (the GDS's own), and one whose key is given in a format not offered
            (
                OBJ.ServerConfiguration_UpdateCertificate,
                update_args(der(plant["gds"][0]), [issuing.der]),
                ua.StatusCodes.BadSecurityChecksFailed,
            ),
            (
                OBJ.ServerConfiguration_UpdateCertificate,
                update_args(der(plant["gds"][0]), [], "PFX", b"\x30\x00"),
                ua.StatusCodes.BadNotSupported,
            ),
        ]
        for method, args, code in refusals:
            result = await call(admin, method, *args)
            assert result.StatusCode.value == code, (method, result.StatusCode)
        assert paths.cert.read_bytes() == before
        # a private key made elsewhere, with its certificate: the server's own check still holds (its URI)
        result = await call(
            admin,
            OBJ.ServerConfiguration_UpdateCertificate,
            *update_args(der(plant["gds"][0]), [issuing.der], "PEM", key_pem(plant["gds"][1])),
        )
        assert result.StatusCode.value == ua.StatusCodes.BadCertificateUriInvalid
        assert paths.cert.read_bytes() == before
    finally:
        await admin.disconnect()


async def test_the_rejected_list_holds_what_was_refused(plant: dict[str, Any], tmp_path: Path) -> None:
    stranger_ca = Authority.root("Stranger CA", key_index=4)
    stranger, stranger_key = stranger_ca.application("urn:stranger", "Stranger", key_index=5)
    refused = await secure_client(plant["app"].endpoint, tmp_path, stranger, stranger_key, "urn:stranger")
    with pytest.raises(ua.UaStatusCodeError):
        await refused.connect()
    admin = await gds_session(plant, tmp_path)
    try:
        result = await call(admin, OBJ.ServerConfiguration_GetRejectedList)
        assert result.StatusCode.is_good()
        assert der(stranger) in result.OutputArguments[0].Value
    finally:
        await admin.disconnect()


TRUST_LIST = ua.NodeId(OBJ.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList)
ADD = ua.NodeId(OBJ.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList_AddCertificate)
REMOVE = ua.NodeId(OBJ.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList_RemoveCertificate)


async def trust_list_call(client: Client, method: ua.NodeId, value: Any, trusted: bool = True) -> ua.StatusCode:
    request = ua.CallMethodRequest()
    request.ObjectId = TRUST_LIST
    request.MethodId = method
    kind = ua.VariantType.ByteString if isinstance(value, bytes) else ua.VariantType.String
    request.InputArguments = [ua.Variant(value, kind), ua.Variant(trusted, ua.VariantType.Boolean)]
    [result] = await client.uaclient.call([request])
    return result.StatusCode


async def test_a_gds_adds_and_removes_trusted_certificates_one_at_a_time(plant: dict[str, Any], tmp_path: Path) -> None:
    """OPC 10000-12 7.8.2.6 and 7.8.2.7 on the DefaultApplicationGroup's TrustList: a client added is let in,
    removed is refused; what the trust list cannot take is refused with the standard's code."""
    paths, issuing = plant["paths"], plant["issuing"]
    mes, _ = issuing.application("urn:plant:line3:mes", "MES", key_index=3)
    contractor = Authority.root("Contractor CA", key_index=4)
    laptop, _ = contractor.application("urn:contractor:laptop", "Laptop", key_index=5)
    old_hmi = application_certificate("urn:plant:old-hmi", "Old HMI", rsa.generate_private_key(65537, 1024))
    admin = await gds_session(plant, tmp_path)
    trusted_before = sorted(p.name for p in paths.trusted.iterdir())
    try:
        refusals = [
            (ADD, b"junk", True, ua.StatusCodes.BadCertificateInvalid),
            (ADD, der(laptop), True, ua.StatusCodes.BadCertificateChainIncomplete),  # its CA is nowhere
            (ADD, contractor.der, False, ua.StatusCodes.BadInvalidArgument),  # an issuer, without its CRLs
            # a key no security policy uacell offers accepts (decision 101)
            (ADD, der(old_hmi), True, ua.StatusCodes.BadCertificatePolicyCheckFailed),
            (REMOVE, "00" * 20, True, ua.StatusCodes.BadInvalidArgument),
            # the plant's root issued the issuing CA in pki/issuers/: removing it would break that chain
            (REMOVE, thumbprint_of(plant["root"].der), True, ua.StatusCodes.BadCertificateChainIncomplete),
        ]
        for method, value, trusted, code in refusals:
            assert (await trust_list_call(admin, method, value, trusted)).value == code, (method, value)
        assert sorted(p.name for p in paths.trusted.iterdir()) == trusted_before
        # the MES, trusted by itself: a chain to the root is not needed for it then
        assert (await trust_list_call(admin, ADD, der(mes))).is_good()
        assert (paths.trusted / f"{thumbprint_of(der(mes))}.der").read_bytes() == der(mes)
        assert (await trust_list_call(admin, REMOVE, thumbprint_of(der(mes)).upper())).is_good()
        assert not (paths.trusted / f"{thumbprint_of(der(mes))}.der").exists()
        # a CA's certificate goes with the revocation lists it signed
        (paths.trusted / "contractor.der").write_bytes(contractor.der)
        (paths.crl / "contractor.crl").write_bytes(contractor.crl())
        assert (await trust_list_call(admin, REMOVE, thumbprint_of(contractor.der))).is_good()
        assert not (paths.trusted / "contractor.der").exists() and not (paths.crl / "contractor.crl").exists()
        assert (paths.crl / "issuing.crl").exists() and (paths.crl / "root.crl").exists()
    finally:
        await admin.disconnect()
    operator = await gds_session(plant, tmp_path, "otto")
    try:
        assert (await trust_list_call(operator, ADD, der(mes))).value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await operator.disconnect()


def thumbprint_of(data: bytes) -> str:
    """OPC UA's thumbprint: the SHA-1 of the DER (OPC 10000-4 7.42, ApplicationInstanceCertificate)."""
    return hashlib.sha1(data).hexdigest()


def _trust_list_method(name: str) -> ua.NodeId:
    return ua.NodeId(getattr(OBJ, f"ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList_{name}"))


async def file_call(client: Client, name: str, *args: ua.Variant) -> ua.CallMethodResult:
    """A method of the DefaultApplicationGroup's TrustList (OPC 10000-12 7.8.2; FileType, OPC 10000-20)."""
    request = ua.CallMethodRequest()
    request.ObjectId = TRUST_LIST
    request.MethodId = _trust_list_method(name)
    request.InputArguments = list(args)
    [result] = await client.uaclient.call([request])
    return result


def u32(value: int) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.UInt32)


async def read_trust_list(client: Client, masks: int = 15) -> bytes:
    opened = await file_call(client, "OpenWithMasks", u32(masks))
    assert opened.StatusCode.is_good(), opened.StatusCode
    handle = opened.OutputArguments[0].Value
    data = b""
    while True:
        result = await file_call(client, "Read", u32(handle), ua.Variant(700, ua.VariantType.Int32))
        assert result.StatusCode.is_good(), result.StatusCode
        if not result.OutputArguments[0].Value:
            break
        data += result.OutputArguments[0].Value
    assert (await file_call(client, "Close", u32(handle))).StatusCode.is_good()
    return data


async def write_trust_list(client: Client, content: bytes) -> ua.CallMethodResult:
    opened = await file_call(client, "Open", ua.Variant(6, ua.VariantType.Byte))  # Write + EraseExisting
    assert opened.StatusCode.is_good(), opened.StatusCode
    handle = opened.OutputArguments[0].Value
    for i in range(0, len(content), 1000):
        written = await file_call(
            client, "Write", u32(handle), ua.Variant(content[i : i + 1000], ua.VariantType.ByteString)
        )
        assert written.StatusCode.is_good(), written.StatusCode
    return await file_call(client, "CloseAndUpdate", u32(handle))


async def reaches(endpoint: str, directory: Path, cert: Any, key: Any, uri: str) -> bool:
    """Does a client with ``cert`` get a secure channel and a session?"""
    client = await secure_client(endpoint, directory, cert, key, uri)
    try:
        await client.connect()
    except (ua.UaError, OSError, TimeoutError):
        return False
    await client.disconnect()
    return True


async def test_a_gds_reads_and_replaces_the_trust_list_as_a_file(plant: dict[str, Any], tmp_path: Path) -> None:
    """OPC 10000-12 7.8.2: the TrustList read through OpenWithMasks and Read is the TrustListDataType of the
    files (decoded here by OPC 10000-6's rules); one written through Open, Write and CloseAndUpdate decides
    which clients get a secure channel, at once."""
    app, paths, root = plant["app"], plant["paths"], plant["root"]
    contractor = Authority.root("Contractor CA", key_index=4)
    laptop, laptop_key = contractor.application("urn:contractor:laptop", "Laptop", key_index=5)
    laptop_dir = tmp_path / "laptop"
    laptop_dir.mkdir()
    admin = await gds_session(plant, tmp_path)
    open_count = admin.get_node(_trust_list_method("OpenCount"))
    last_update = admin.get_node(_trust_list_method("LastUpdateTime"))
    try:
        masks, (trusted, trusted_crls, issuers, issuer_crls) = parse_trust_list(await read_trust_list(admin))
        assert masks == 15
        assert trusted == [root.der] and issuers == [plant["issuing"].der]
        assert trusted_crls == [(paths.crl / "root.crl").read_bytes()]
        assert issuer_crls == [(paths.crl / "issuing.crl").read_bytes()]
        assert parse_trust_list(await read_trust_list(admin, 4)) == (4, [None, None, [plant["issuing"].der], None])
        assert await admin.get_node(_trust_list_method("MaxByteStringLength")).read_value() > 0
        assert await open_count.read_value() == 0
        assert not await reaches(app.endpoint, laptop_dir, laptop, laptop_key, "urn:contractor:laptop")
        before = await last_update.read_value()

        # the contractor's CA trusted, with its revocation list: the laptop gets in
        root_crl, contractor_crl = (paths.crl / "root.crl").read_bytes(), contractor.crl()
        content = trust_list_bytes(3, [root.der, contractor.der], [root_crl, contractor_crl])
        result = await write_trust_list(admin, content)
        assert result.StatusCode.is_good(), result.StatusCode
        assert result.OutputArguments[0].Value is False  # applied at once
        assert sorted(p.name for p in paths.trusted.iterdir()) == sorted(
            [f"{thumbprint_of(root.der)}.der", f"{thumbprint_of(contractor.der)}.der"]
        )
        assert (paths.issuers / "issuing.der").exists()  # the issuers were not specified
        assert await open_count.read_value() == 0
        assert await last_update.read_value() > before
        connected = await secure_client(app.endpoint, laptop_dir, laptop, laptop_key, "urn:contractor:laptop")
        await connected.connect()
        assert await connected.nodes.server_state.read_value() == ua.ServerState.Running

        # and out again: the laptop's open channel is closed (OPC 10000-12 7.8.2.5), a new one refused
        result = await write_trust_list(admin, trust_list_bytes(3, [root.der], [root_crl]))
        assert result.StatusCode.is_good(), result.StatusCode
        with pytest.raises((ua.UaError, ConnectionError, TimeoutError)):
            await connected.nodes.server_state.read_value()
        assert not await reaches(app.endpoint, laptop_dir, laptop, laptop_key, "urn:contractor:laptop")
        assert await admin.nodes.server_state.read_value() == ua.ServerState.Running  # the GDS's is kept
        assert parse_trust_list(await read_trust_list(admin, 3)) == (3, [[root.der], [root_crl], None, None])
    finally:
        await admin.disconnect()
        with contextlib.suppress(Exception):
            await connected.disconnect()


async def test_what_the_trust_list_file_refuses_changes_nothing(plant: dict[str, Any], tmp_path: Path) -> None:
    paths = plant["paths"]

    def files() -> dict[str, bytes]:
        return {
            f"{d.name}/{f.name}": f.read_bytes() for d in (paths.trusted, paths.issuers, paths.crl) for f in d.iterdir()
        }

    before = files()
    admin = await gds_session(plant, tmp_path)
    other = await gds_session(plant, tmp_path)
    try:
        result = await file_call(admin, "Open", ua.Variant(3, ua.VariantType.Byte))  # Read + Write
        assert result.StatusCode.value == ua.StatusCodes.BadNotSupported
        opened = await file_call(admin, "Open", ua.Variant(6, ua.VariantType.Byte))
        handle = opened.OutputArguments[0].Value
        assert await admin.get_node(_trust_list_method("OpenCount")).read_value() == 1
        refusals = [
            (other, "Open", [ua.Variant(1, ua.VariantType.Byte)], ua.StatusCodes.BadNotReadable),
            (
                other,
                "Write",
                [u32(handle), ua.Variant(b"x", ua.VariantType.ByteString)],
                ua.StatusCodes.BadInvalidArgument,
            ),
            (admin, "Read", [u32(handle), ua.Variant(10, ua.VariantType.Int32)], ua.StatusCodes.BadInvalidState),
        ]
        for client, name, args, code in refusals:
            assert (await file_call(client, name, *args)).StatusCode.value == code, name
        mes, _ = plant["issuing"].application("urn:plant:line3:mes", "MES", key_index=3)
        assert (await trust_list_call(admin, ADD, der(mes))).value == ua.StatusCodes.BadInvalidState  # it is open
        written = await file_call(admin, "Write", u32(handle), ua.Variant(b"\x01\x00\x00", ua.VariantType.ByteString))
        assert written.StatusCode.is_good()
        result = await file_call(admin, "CloseAndUpdate", u32(handle))
        assert result.StatusCode.value == ua.StatusCodes.BadDecodingError
        assert await admin.get_node(_trust_list_method("OpenCount")).read_value() == 0  # closed all the same
        result = await write_trust_list(admin, trust_list_bytes(1, [b"not a certificate"]))
        assert result.StatusCode.value == ua.StatusCodes.BadCertificateInvalid
        assert files() == before
    finally:
        await other.disconnect()
        await admin.disconnect()
    operator = await gds_session(plant, tmp_path, "otto")
    try:
        result = await file_call(operator, "OpenWithMasks", u32(15))
        assert result.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    finally:
        await operator.disconnect()
    signed = await gds_session(plant, tmp_path, mode=ua.MessageSecurityMode.Sign)
    try:
        result = await file_call(signed, "OpenWithMasks", u32(15))
        assert result.StatusCode.value == ua.StatusCodes.BadSecurityModeInsufficient
    finally:
        await signed.disconnect()


async def test_trust_list_handles_end_with_their_session_or_after_the_activity_timeout(
    plant: dict[str, Any], tmp_path: Path
) -> None:
    """OPC 10000-12 7.8.2.1: the Server closes a TrustList left open (its ActivityTimeout), and a handle lives no
    longer than its session: a GDS that went away does not lock the trust list."""
    app = plant["app"]
    trust_file = app.server_configuration.trust_file
    first = await gds_session(plant, tmp_path)
    second = await gds_session(plant, tmp_path)
    open_count = second.get_node(_trust_list_method("OpenCount"))
    try:
        timeout = await second.get_node(_trust_list_method("ActivityTimeout")).read_value()
        assert timeout == trust_file.activity_timeout * 1000  # a Duration, ms
        assert (await file_call(first, "Open", ua.Variant(6, ua.VariantType.Byte))).StatusCode.is_good()
        assert await open_count.read_value() == 1
        await first.disconnect()  # its session closed: its handle with it
        await wait_until_value(open_count, 0)
        opened = await file_call(second, "Open", ua.Variant(6, ua.VariantType.Byte))
        assert opened.StatusCode.is_good(), opened.StatusCode
        trust_file.activity_timeout = 0.5  # no call for half a second now closes the list
        touched = await file_call(second, "GetPosition", u32(opened.OutputArguments[0].Value))
        assert touched.StatusCode.is_good() and touched.OutputArguments[0].Value == 0
        await wait_until_value(open_count, 0)
        late = await file_call(
            second, "Write", u32(opened.OutputArguments[0].Value), ua.Variant(b"x", ua.VariantType.ByteString)
        )
        assert late.StatusCode.value == ua.StatusCodes.BadInvalidArgument  # the handle is gone
    finally:
        trust_file.activity_timeout = 60.0
        await second.disconnect()
        with contextlib.suppress(Exception):
            await first.disconnect()


async def wait_until_value(node: Any, value: Any, timeout: float = 10.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while (seen := await node.read_value()) != value:
        assert asyncio.get_running_loop().time() < deadline, f"{node.nodeid} is {seen}, not {value}"
        await asyncio.sleep(0.05)
