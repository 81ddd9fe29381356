"""The server's certificate issued by a plant's CA (decision 95): a PKCS #10 request the CA signs
(tests/plant_ca.py, made from RFC 2986/5280 and OPC 10000-6 6.2.2, not from uacell's code), the install
and its refusals, a crash in the middle, the start that keeps a CA's certificate; over TCP, the chain
in the endpoints (OPC 10000-6 6.2.6) and sessions of an asyncua client that knows only the root."""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID
from helpers import secure_client
from plant_ca import Authority, der, pem

from uacell.security.chain import split_chain
from uacell.security.own_certificate import (
    InstallRefused,
    finish_install,
    install_certificate,
    own_issuers,
    signing_request,
)
from uacell.security.pki import PkiPaths, ensure_server_certificate

URI = "urn:plant:line3:uacell"
HOSTS = ["127.0.0.1"]


def now() -> dt.datetime:
    """The time of the check, taken when it runs: a module-level "now" is from collection, which a slow
    run puts minutes before certificates a test makes."""
    return dt.datetime.now(dt.UTC)


@pytest.fixture(scope="module")
def plant() -> Iterator[dict[str, Authority]]:
    root = Authority.root()
    yield {"root": root, "issuing": root.intermediate()}


@pytest.fixture
def paths(tmp_path: Path) -> PkiPaths:
    """A data directory whose server made its self-signed certificate at first start."""
    p = PkiPaths.in_data_dir(tmp_path / "data")
    ensure_server_certificate(p, URI, HOSTS)
    return p


def own_files(paths: PkiPaths) -> dict[str, bytes]:
    return {str(f.relative_to(paths.own)): f.read_bytes() for f in sorted(paths.own.rglob("*")) if f.is_file()}


def server_public(paths: PkiPaths, pending: bool = False) -> rsa.RSAPublicNumbers:
    key = serialization.load_pem_private_key((paths.pending_key if pending else paths.key).read_bytes(), None)
    assert isinstance(key, rsa.RSAPrivateKey)
    return key.public_key().public_numbers()


# the request and the install, pure ----------------------------------------------------------------------


def test_a_request_asks_for_what_a_server_certificate_holds(paths: PkiPaths) -> None:
    request = x509.load_pem_x509_csr(signing_request(paths, URI, HOSTS))
    assert request.is_signature_valid
    assert request.public_key().public_numbers() == server_public(paths)  # type: ignore[union-attr]
    san = request.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [URI]
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    usage = request.extensions.get_extension_for_class(x509.KeyUsage).value
    assert usage.digital_signature and usage.key_encipherment and not usage.key_cert_sign
    extended = request.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(extended) == [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
    assert not request.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert not paths.pending_key.exists()


def test_the_certificate_the_ca_issued_is_installed_with_its_chain(
    paths: PkiPaths, plant: dict[str, Authority]
) -> None:
    before = own_files(paths)
    issued = plant["issuing"].sign_request(signing_request(paths, URI, HOSTS))
    done = install_certificate(paths, pem(issued) + pem(plant["issuing"].cert) + pem(plant["root"].cert), URI, HOSTS)
    assert done.certificate == issued and not done.new_key and done.warnings == ()
    assert paths.cert.read_bytes() == der(issued)
    assert split_chain(b"".join(der(c) for c in x509.load_pem_x509_certificates(paths.chain.read_bytes()))) == [
        plant["issuing"].cert,
        plant["root"].cert,
    ]
    assert own_issuers(paths, issued) == [plant["issuing"].cert, plant["root"].cert]
    assert paths.key.read_bytes() == before["key.pem"]  # the same key
    backups = {f.name.split("-")[0]: f.read_bytes() for f in paths.backup.iterdir()}
    assert backups == {"cert": before["cert.der"], "key": before["key.pem"]}
    # DER appended, the root left out (clients have it), is as good
    again = plant["issuing"].sign_request(signing_request(paths, URI, HOSTS))
    install_certificate(paths, der(again) + plant["issuing"].der, URI, HOSTS)
    assert paths.cert.read_bytes() == der(again)
    assert own_issuers(paths, again) == [plant["issuing"].cert]


def _another_key_request(tmp_path: Path) -> bytes:
    other = PkiPaths.in_data_dir(tmp_path / "other")
    ensure_server_certificate(other, URI, HOSTS)
    return signing_request(other, URI, HOSTS)


REFUSALS: dict[str, tuple[Any, str]] = {
    "another key's": (
        lambda p, ca, tmp: [ca["issuing"].sign_request(_another_key_request(tmp))],
        "not the certificate of the server's key",
    ),
    "without the URI": (
        lambda p, ca, tmp: [ca["issuing"].sign_request(signing_request(p, URI, HOSTS), names=[x509.DNSName("h")])],
        f"application URI {URI} missing",
    ),
    "without the host": (
        lambda p, ca, tmp: [
            ca["issuing"].sign_request(signing_request(p, URI, HOSTS), names=[x509.UniformResourceIdentifier(URI)])
        ],
        "address 127.0.0.1 missing",
    ),
    "expired": (
        lambda p, ca, tmp: [
            ca["issuing"].sign_request(signing_request(p, URI, HOSTS), not_before=now() - dt.timedelta(days=400))
        ],
        "it expired on",
    ),
    "not yet valid": (
        lambda p, ca, tmp: [
            ca["issuing"].sign_request(signing_request(p, URI, HOSTS), not_before=now() + dt.timedelta(days=2))
        ],
        "it is not valid before",
    ),
    "for signing only": (
        lambda p, ca, tmp: [ca["issuing"].sign_request(signing_request(p, URI, HOSTS), usages=("digital_signature",))],
        "does not allow keyEncipherment",
    ),
    "for clients only": (
        lambda p, ca, tmp: [
            ca["issuing"].sign_request(signing_request(p, URI, HOSTS), extended=(ExtendedKeyUsageOID.CLIENT_AUTH,))
        ],
        "does not allow serverAuth",
    ),
    "its CAs out of order": (
        lambda p, ca, tmp: [
            ca["issuing"].sign_request(signing_request(p, URI, HOSTS)),
            ca["root"].cert,
            ca["issuing"].cert,
        ],
        "certificate 2 of the file did not issue certificate 1",
    ),
    "followed by no CA": (
        lambda p, ca, tmp: [
            ca["root"].sign_request(signing_request(p, URI, HOSTS)),
            ca["root"].intermediate("Not a CA", ca=False).cert,
        ],
        "certificate 2 of the file did not issue certificate 1",
    ),
}


# what a client is told of each (OPC 10000-12 UpdateCertificate, decision 96)
CODES = {
    "another key's": "BadSecurityChecksFailed",
    "without the URI": "BadCertificateUriInvalid",
    "without the host": "BadCertificateHostNameInvalid",
    "expired": "BadCertificateTimeInvalid",
    "not yet valid": "BadCertificateTimeInvalid",
    "for signing only": "BadCertificateUseNotAllowed",
    "for clients only": "BadCertificateUseNotAllowed",
    "its CAs out of order": "BadSecurityChecksFailed",
    "followed by no CA": "BadSecurityChecksFailed",
}


@pytest.mark.parametrize("case", REFUSALS)
def test_what_cannot_be_the_servers_certificate_is_refused_and_nothing_changes(
    case: str, paths: PkiPaths, plant: dict[str, Authority], tmp_path: Path
) -> None:
    make, why = REFUSALS[case]
    certs = make(paths, plant, tmp_path)
    before = own_files(paths)
    with pytest.raises(InstallRefused) as refused:
        install_certificate(paths, b"".join(pem(c) for c in certs), URI, HOSTS)
    assert why in str(refused.value)
    assert refused.value.code == CODES[case]
    assert own_files(paths) == before


def test_a_ca_below_the_server_certificate_must_be_allowed_to_sign_certificates(
    paths: PkiPaths, plant: dict[str, Authority]
) -> None:
    not_ca = plant["root"].intermediate("Plant Web CA", ca=False, key_index=6)
    issued = not_ca.sign_request(signing_request(paths, URI, HOSTS))
    before = own_files(paths)
    with pytest.raises(InstallRefused, match="certificate 2 of the file is not a CA's certificate"):
        install_certificate(paths, pem(issued) + pem(not_ca.cert), URI, HOSTS)
    for junk in (b"", b"junk", b"-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n"):
        with pytest.raises(InstallRefused, match="not a certificate file"):
            install_certificate(paths, junk, URI, HOSTS)
    assert own_files(paths) == before


def test_a_new_key_waits_until_its_certificate_is_installed(paths: PkiPaths, plant: dict[str, Authority]) -> None:
    old_key = paths.key.read_bytes()
    request = signing_request(paths, URI, HOSTS, new_key=True)
    assert paths.pending_key.stat().st_mode & 0o777 == 0o600
    assert paths.key.read_bytes() == old_key  # the server goes on with its key meanwhile
    pending = server_public(paths, pending=True)
    assert x509.load_pem_x509_csr(request).public_key().public_numbers() == pending  # type: ignore[union-attr]
    done = install_certificate(paths, pem(plant["issuing"].sign_request(request)), URI, HOSTS)
    assert done.new_key
    assert server_public(paths) == pending and not paths.pending_key.exists()
    assert not paths.chain.exists()  # no CA certificate came with it
    assert not paths.key_checked.exists()  # the new key is checked once, at the next start


def test_an_install_a_crash_cut_short_is_finished_at_the_next_start(
    paths: PkiPaths, plant: dict[str, Authority]
) -> None:
    request = signing_request(paths, URI, HOSTS, new_key=True)
    issued = plant["issuing"].sign_request(request)
    # the crash: the certificate written, its key still pending
    paths.cert.write_bytes(der(issued))
    pending = server_public(paths, pending=True)
    assert finish_install(paths)
    assert server_public(paths) == pending and not paths.pending_key.exists()
    ensure_server_certificate(paths, URI, HOSTS)
    assert paths.cert.read_bytes() == der(issued)
    assert not finish_install(paths)  # nothing pending any more


def test_a_pending_key_without_its_certificate_changes_nothing(paths: PkiPaths) -> None:
    before = own_files(paths)
    signing_request(paths, URI, HOSTS, new_key=True)
    assert not finish_install(paths)
    assert paths.key.read_bytes() == before["key.pem"] and paths.pending_key.exists()


def test_a_start_keeps_a_certificate_of_the_ca_that_no_longer_fits_and_says_so(
    paths: PkiPaths, plant: dict[str, Authority], caplog: pytest.LogCaptureFixture
) -> None:
    issued = plant["issuing"].sign_request(signing_request(paths, URI, HOSTS), days=20)
    done = install_certificate(paths, pem(issued) + pem(plant["issuing"].cert), URI, HOSTS)
    assert done.warnings and "expires on" in done.warnings[0]
    kept = own_files(paths)
    caplog.set_level(logging.WARNING, logger="uacell.security.pki")
    ensure_server_certificate(paths, URI, [*HOSTS, "127.0.0.2"])  # expires in 20 days, a host it lacks
    assert own_files(paths) == kept
    [line] = [r.getMessage() for r in caplog.records]
    assert "it is kept" in line and "uacell cert request" in line
    assert "address 127.0.0.2 missing" in line and "expires" in line
    # a self-signed certificate that no longer fits is remade, as before
    self_signed = PkiPaths.in_data_dir(paths.root.parent / "other")
    ensure_server_certificate(self_signed, URI, HOSTS)
    first = self_signed.cert.read_bytes()
    ensure_server_certificate(self_signed, URI, [*HOSTS, "127.0.0.2"])
    assert self_signed.cert.read_bytes() != first


def test_a_chain_file_that_is_not_the_certificates_chain_is_not_sent(
    paths: PkiPaths, plant: dict[str, Authority], caplog: pytest.LogCaptureFixture
) -> None:
    issued = plant["issuing"].sign_request(signing_request(paths, URI, HOSTS))
    install_certificate(paths, pem(issued) + pem(plant["issuing"].cert), URI, HOSTS)
    paths.chain.write_bytes(pem(Authority.root("Contractor CA", key_index=4).cert))
    with caplog.at_level(logging.WARNING, logger="uacell.security.own_certificate"):
        assert own_issuers(paths, issued) == []
    assert "is not the chain of the server's certificate" in caplog.text


# over TCP: what a client receives ---------------------------------------------------------------------

MES = "urn:plant:line3:mes"


@pytest.mark.asyncio
async def test_the_server_sends_its_ca_chain_and_a_client_of_the_plant_gets_a_session(
    tmp_path: Path, plant: dict[str, Authority]
) -> None:
    root, issuing = plant["root"], plant["issuing"]
    config = fast_config(tmp_path / "data")
    uri, hosts = config.server.application_uri, [config.server.host]
    paths = PkiPaths.in_data_dir(config.server.data_dir)
    ensure_server_certificate(paths, uri, hosts)
    issued = issuing.sign_request(signing_request(paths, uri, hosts))
    install_certificate(paths, pem(issued) + pem(issuing.cert), uri, hosts)
    # the client's certificate comes from the same CA; the server trusts the root (decision 92)
    mes, mes_key = issuing.application(MES)
    (paths.trusted / "root.der").write_bytes(root.der)
    (paths.issuers / "issuing.der").write_bytes(issuing.der)
    (paths.crl / "root.crl").write_bytes(root.crl())
    (paths.crl / "issuing.crl").write_bytes(issuing.crl())
    app = await start_app(config)
    try:
        endpoints = await Client(app.endpoint, timeout=20).connect_and_get_server_endpoints()
        assert {e.ServerCertificate for e in endpoints} == {der(issued) + issuing.der}
        # what a client that trusts the plant's root alone checks: the chain it was sent reaches the root
        sent = split_chain(endpoints[0].ServerCertificate)
        sent[0].verify_directly_issued_by(sent[1])
        sent[1].verify_directly_issued_by(root.cert)
        for signs_over_the_chain in (False, True):
            created: list[bytes] = []
            client = await plant_client(app.endpoint, tmp_path, (mes, mes_key), created, signs_over_the_chain)
            try:
                assert created == [der(issued) + issuing.der]
                assert await client.nodes.server_state.read_value() == ua.ServerState.Running
            finally:
                await client.disconnect()
        # a signature over something else is still refused
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await plant_client(app.endpoint, tmp_path, (mes, mes_key), [], signs_over_the_chain=True, extra=b"x")
        assert refused.value.code == ua.StatusCodes.BadApplicationSignatureInvalid
    finally:
        await app.stop()


async def plant_client(
    endpoint: str,
    tmp_path: Path,
    mes: tuple[Any, Any],
    created: list[bytes],
    signs_over_the_chain: bool,
    extra: bytes = b"",
) -> Client:
    """The MES client over Basic256Sha256 SignAndEncrypt; ``created``: the serverCertificate each
    CreateSession answered. asyncua signs ActivateSession over the server's certificate alone, as OPC
    10000-4 5.7.3.2 asks; ``signs_over_the_chain``: over the whole serverCertificate it was sent
    (followed by ``extra``), as clients did before the errata of 1.04."""
    client = await secure_client(endpoint, tmp_path, mes[0], mes[1], MES)
    create = client.uaclient.create_session

    async def create_session(params: ua.CreateSessionParameters) -> Any:
        response = await create(params)
        created.append(response.ServerCertificate)
        return response

    client.uaclient.create_session = create_session
    if signs_over_the_chain:
        activate = client.activate_session

        async def activate_session(*args: Any, **kwargs: Any) -> Any:
            # what asyncua signs at ActivateSession: this certificate, then the server nonce
            client.security_policy.peer_certificate = created[-1] + extra
            return await activate(*args, **kwargs)

        client.activate_session = activate_session
    await client.connect()
    return client
