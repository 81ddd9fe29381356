"""Server certificate, trust list and the asyncua certificate validator."""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import shutil
import socket
import stat
from pathlib import Path

import pytest
from asyncua import Client, Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID

from uacell.config import load_config
from uacell.core.errors import ConfigError
from uacell.security.pki import (
    CertificateValidator,
    PkiPaths,
    RejectedLimit,
    TrustList,
    ensure_server_certificate,
    generate_key,
    load_server_key,
    make_client_certificate,
    prune_rejected,
    thumbprint,
)

SERVER_URI = "urn:uacell:test:server"
CLIENT_URI = "urn:uacell:test:client"


@pytest.fixture(scope="module")
def key() -> rsa.RSAPrivateKey:
    return generate_key()


@pytest.fixture(scope="module")
def client_cert(key: rsa.RSAPrivateKey) -> tuple[bytes, bytes]:
    return make_client_certificate(CLIENT_URI, key=key)


@pytest.fixture
def paths(tmp_path: Path) -> PkiPaths:
    return PkiPaths.in_data_dir(tmp_path)


def app(uri: str = CLIENT_URI) -> ua.ApplicationDescription:
    d = ua.ApplicationDescription()
    d.ApplicationUri = uri
    d.ApplicationType = ua.ApplicationType.Client
    return d


def test_first_start_creates_a_fitting_certificate(paths: PkiPaths, key: rsa.RSAPrivateKey) -> None:
    hosts = ["127.0.0.1", "plc-gw.example"]
    cert_path, key_path = ensure_server_certificate(paths, SERVER_URI, hosts, key=key)
    assert (cert_path, key_path) == (paths.cert, paths.key)
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    assert paths.trusted.is_dir() and paths.rejected.is_dir()
    cert = x509.load_der_x509_certificate(cert_path.read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [SERVER_URI]
    assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "plc-gw.example"}
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
    ku = cert.extensions.get_extension_for_class(x509.KeyUsage).value
    assert (
        ku.digital_signature,
        ku.content_commitment,
        ku.key_encipherment,
        ku.data_encipherment,
        ku.key_cert_sign,
    ) == (True, True, True, True, True)
    eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    assert isinstance(cert.signature_hash_algorithm, hashes.SHA256)
    public = cert.public_key()
    assert isinstance(public, rsa.RSAPublicKey)  # OPC UA's RSA policies
    assert public.key_size >= 2048
    assert cert.not_valid_after_utc - cert.not_valid_before_utc > dt.timedelta(days=3 * 365)
    loaded = serialization.load_pem_private_key(key_path.read_bytes(), None)
    assert isinstance(loaded, rsa.RSAPrivateKey)
    assert loaded.public_key().public_numbers() == public.public_numbers()


def test_the_server_key_is_checked_once_per_key(
    paths: PkiPaths, key: rsa.RSAPrivateKey, monkeypatch: pytest.MonkeyPatch
) -> None:
    """cryptography's RSA consistency check (30 ms) runs for a key file uacell has not seen pass it:
    not for the key it made, again for a key put there by hand, not for that one the next time."""
    checks: list[bool] = []
    real = serialization.load_pem_private_key

    def spy(data: bytes, password: bytes | None, *, unsafe_skip_rsa_key_validation: bool = False) -> object:
        checks.append(not unsafe_skip_rsa_key_validation)
        return real(data, password, unsafe_skip_rsa_key_validation=unsafe_skip_rsa_key_validation)

    monkeypatch.setattr(serialization, "load_pem_private_key", spy)
    ensure_server_certificate(paths, SERVER_URI, ["127.0.0.1"], key=key)
    loaded = load_server_key(paths)
    assert loaded.private_numbers() == key.private_numbers() and checks == [False]  # uacell made it
    other = generate_key()
    paths.key.write_bytes(other.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ))  # fmt: skip
    assert load_server_key(paths).private_numbers() == other.private_numbers() and checks == [False, True]
    assert load_server_key(paths).private_numbers() == other.private_numbers() and checks == [False, True, False]
    paths.key.write_bytes(b"-----BEGIN PRIVATE KEY-----\nbroken\n-----END PRIVATE KEY-----\n")
    with pytest.raises(ValueError):
        load_server_key(paths)
    assert checks[-1] is True  # a changed file is checked (and here refused)


def test_wildcard_host_puts_this_machine_in_the_certificate(paths: PkiPaths, key: rsa.RSAPrivateKey) -> None:
    ensure_server_certificate(paths, SERVER_URI, ["0.0.0.0"], key=key)
    cert = x509.load_der_x509_certificate(paths.cert.read_bytes())
    dns = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(x509.DNSName)
    assert socket.gethostname() in dns


def test_certificate_is_reused_then_remade_when_hosts_change(paths: PkiPaths, key: rsa.RSAPrivateKey) -> None:
    ensure_server_certificate(paths, SERVER_URI, ["127.0.0.1"], key=key)
    first = paths.cert.read_bytes()
    ensure_server_certificate(paths, SERVER_URI, ["localhost", "127.0.0.1"], key=key)
    assert paths.cert.read_bytes() == first  # "localhost" was already covered
    assert not paths.backup.exists()
    ensure_server_certificate(paths, SERVER_URI, ["127.0.0.1", "10.1.2.3"], key=key)
    second = paths.cert.read_bytes()
    assert second != first
    backups = sorted(p.name for p in paths.backup.iterdir())
    assert len(backups) == 2 and backups[0].startswith("cert-") and backups[1].startswith("key-")
    assert (paths.backup / backups[0]).read_bytes() == first
    ensure_server_certificate(paths, "urn:other", ["127.0.0.1", "10.1.2.3"], key=key)
    assert paths.cert.read_bytes() != second  # a new application URI needs a new certificate


def test_untrusted_certificate_is_rejected_with_instructions(
    paths: PkiPaths, client_cert: tuple[bytes, bytes], caplog: pytest.LogCaptureFixture
) -> None:
    der, _ = client_cert
    trust = TrustList(paths)
    with caplog.at_level(logging.WARNING, logger="uacell.security.pki"):
        assert trust.admit(der, CLIENT_URI) is False
    rejected = list(paths.rejected.iterdir())
    assert len(rejected) == 1 and rejected[0].read_bytes() == der
    assert thumbprint(der) in rejected[0].name
    assert f"move {rejected[0]} to {paths.trusted}/" in caplog.text
    # The operator does what the log line says:
    shutil.move(rejected[0], paths.trusted / rejected[0].name)
    assert trust.admit(der, CLIENT_URI) is True


def test_pem_files_in_trusted_count(paths: PkiPaths, client_cert: tuple[bytes, bytes]) -> None:
    der, _ = client_cert
    pem = x509.load_der_x509_certificate(der).public_bytes(serialization.Encoding.PEM)
    trust = TrustList(paths)
    (paths.trusted / "client.pem").write_bytes(pem)
    (paths.trusted / "README.txt").write_text("not a certificate")
    (paths.trusted / "broken.der").write_bytes(b"junk")
    assert trust.is_trusted(der)
    other, _ = make_client_certificate("urn:other", key=generate_key())
    assert not trust.is_trusted(other)


def test_trust_on_first_use(paths: PkiPaths, client_cert: tuple[bytes, bytes]) -> None:
    der, _ = client_cert
    trust = TrustList(paths, trust_on_first_use=True)
    assert trust.admit(der, CLIENT_URI) is True
    assert [p.read_bytes() for p in paths.trusted.iterdir()] == [der]
    assert list(paths.rejected.iterdir()) == []
    assert TrustList(paths).is_trusted(der)  # remembered without the switch


async def test_validator_refuses_untrusted_then_accepts_trusted(
    paths: PkiPaths, client_cert: tuple[bytes, bytes]
) -> None:
    der, _ = client_cert
    cert = x509.load_der_x509_certificate(der)
    validate = CertificateValidator(TrustList(paths))
    with pytest.raises(ServiceError) as info:
        await validate(cert, app())
    assert info.value.code == ua.StatusCodes.BadCertificateUntrusted
    TrustList(paths).trust(der)
    await validate(cert, app())


async def test_validator_checks_uri_and_time_before_trusting_on_first_use(
    paths: PkiPaths, key: rsa.RSAPrivateKey
) -> None:
    validate = CertificateValidator(TrustList(paths, trust_on_first_use=True))
    der, _ = make_client_certificate(CLIENT_URI, key=key)
    with pytest.raises(ServiceError) as info:
        await validate(x509.load_der_x509_certificate(der), app("urn:someone:else"))
    assert info.value.code == ua.StatusCodes.BadCertificateUriInvalid
    old = dt.datetime.now(dt.UTC) - dt.timedelta(days=30)
    expired, _ = make_client_certificate(CLIENT_URI, key=key, days=10, not_before=old)
    with pytest.raises(ServiceError) as info:
        await validate(x509.load_der_x509_certificate(expired), app())
    assert info.value.code == ua.StatusCodes.BadCertificateTimeInvalid
    assert list(paths.trusted.iterdir()) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def test_asyncua_server_uses_the_validator(
    tmp_path: Path, paths: PkiPaths, key: rsa.RSAPrivateKey, client_cert: tuple[bytes, bytes]
) -> None:
    """Over a real Basic256Sha256 channel: refused until the rejected file is moved to trusted/."""
    cert_path, key_path = ensure_server_certificate(paths, SERVER_URI, ["127.0.0.1"], key=key)
    server = Server()
    await server.init()
    url = f"opc.tcp://127.0.0.1:{_free_port()}/"
    server.set_endpoint(url)
    await server.set_application_uri(SERVER_URI)
    server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
    await server.load_certificate(str(cert_path))
    await server.load_private_key(str(key_path))
    server.set_certificate_validator(CertificateValidator(TrustList(paths)))
    der, pem = client_cert
    (tmp_path / "client.der").write_bytes(der)
    (tmp_path / "client.pem").write_bytes(pem)

    async def connect() -> None:
        client = Client(url, timeout=5)
        client.application_uri = CLIENT_URI
        await client.set_security(
            SecurityPolicyBasic256Sha256,
            str(tmp_path / "client.der"),
            str(tmp_path / "client.pem"),
            server_certificate=str(cert_path),
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )
        async with client:
            assert await client.nodes.server_state.read_value() == ua.ServerState.Running

    async with server:
        with pytest.raises(ua.UaStatusCodeError) as info:
            await connect()
        assert info.value.code == ua.StatusCodes.BadCertificateUntrusted
        [rejected] = paths.rejected.iterdir()
        shutil.move(rejected, paths.trusted / rejected.name)
        await connect()


# pki/rejected/ cap ------------------------------------------------------------------------------------


def _rejected_files(directory: Path, ages: list[float], now: float) -> list[Path]:
    """Certificate files in ``directory``, the i-th ``ages[i]`` seconds old."""
    directory.mkdir(parents=True, exist_ok=True)
    files = []
    for i, age in enumerate(ages):
        f = directory / f"cert{i} [{i:040x}].der"
        f.write_bytes(b"x")
        os.utime(f, (now - age, now - age))
        files.append(f)
    return files


def test_prune_rejected_drops_aged_then_oldest_beyond_the_count(tmp_path: Path) -> None:
    now = 1_000_000.0
    files = _rejected_files(tmp_path, [500.0, 10.0, 2000.0, 30.0, 20.0], now)
    (tmp_path / "notes.txt").write_text("not a certificate")
    dropped = prune_rejected(tmp_path, RejectedLimit(max_files=2, max_age=1000.0), now=now)
    # aged first (2000 s), then the oldest of the rest (500 s, 30 s); the two newest stay
    assert dropped == [files[2], files[0], files[3]]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([files[1].name, files[4].name, "notes.txt"])
    assert prune_rejected(tmp_path, RejectedLimit(max_files=2, max_age=1000.0), now=now) == []


def test_trust_list_caps_rejected_and_logs_once(paths: PkiPaths, caplog: pytest.LogCaptureFixture) -> None:
    trust_list = TrustList(paths, rejected_limit=RejectedLimit(max_files=3, max_age=86400.0))
    caplog.set_level(logging.WARNING, logger="uacell.security.pki")
    key = generate_key()
    ders = [make_client_certificate(CLIENT_URI, key=key, common_name=f"flood {i}")[0] for i in range(6)]
    start = dt.datetime.now().timestamp() - 100
    for i, der in enumerate(ders):
        path = trust_list.reject(der)
        os.utime(path, (start + i, start + i))  # strictly increasing, all within the age limit
    kept = sorted(p.name for p in paths.rejected.iterdir())
    assert kept == sorted(f"{thumbprint(d)}.der" for i, d in enumerate(ders) if i >= 3)
    assert len([r for r in caplog.records if "keeps at most 3" in r.getMessage()]) == 1


def test_trust_list_start_drops_aged_rejected(paths: PkiPaths) -> None:
    old = _rejected_files(paths.rejected, [40 * 86400.0, 60.0], dt.datetime.now().timestamp())
    TrustList(paths, rejected_limit=RejectedLimit(max_files=10, max_age=30 * 86400.0))
    assert [p.name for p in paths.rejected.iterdir()] == [old[1].name]


def test_rejected_limits_come_from_the_configuration(tmp_path: Path) -> None:
    cfg = tmp_path / "uacell.toml"
    cfg.write_text("[server]\nrejected_max_files = 7\nrejected_max_age_days = 2\n")
    config = load_config(cfg)
    assert (config.server.rejected_max_files, config.server.rejected_max_age_days) == (7, 2.0)
    cfg.write_text("[server]\nrejected_max_files = 0\n")
    with pytest.raises(ConfigError, match="rejected_max_files"):
        load_config(cfg)
    cfg.write_text("[server]\nrejected_max_age_days = -1\n")
    with pytest.raises(ConfigError, match="rejected_max_age_days"):
        load_config(cfg)
