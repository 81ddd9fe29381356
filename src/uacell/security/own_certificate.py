"""The server's own certificate issued by a plant's CA (decision 95).

``uacell cert request`` makes a certificate signing request (PKCS #10, RFC 2986) for the server's key,
or for a new key kept in ``pki/own/pending/`` until its certificate comes back; it asks for what a
server's Application Instance Certificate holds (OPC 10000-6 6.2.2): the application URI and the host
names and addresses it listens on in subjectAltName, the key usages, serverAuth and clientAuth.

``uacell cert install FILE`` takes the certificate the CA issued, followed by the CA's own certificates
up to (not necessarily including) its root, PEM or DER. It is refused, nothing changed, unless

- it is the certificate of the server's key or of the pending one;
- it is valid now and names the application URI and the listening hosts (``pki.coverage_problems``);
- its key usages allow signing and key encipherment, and an extended key usage, if any, serverAuth;
- every certificate after it issued the one before and is a CA that may sign certificates.

The old pair goes to ``pki/own/backup/``; the CA's certificates go to ``pki/own/chain.pem`` and are sent
after the server's wherever it sends its certificate (OPC 10000-6 6.2.6). The files are written in an
order a crash cannot break: the chain, the certificate, then the pending key (``finish_install``
completes an install a crash cut short, at the next start).

A certificate a CA issued is never replaced by uacell at start-up (``pki.ensure_server_certificate``):
when it no longer fits, uacell says so at every start and keeps it.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID

from uacell.core.files import atomic_write
from uacell.security.chain import der_of, issued_by, may_sign_certificates, split_chain
from uacell.security.pki import (
    RENEW_BEFORE,
    PkiPaths,
    application_key_usage,
    application_names,
    back_up,
    coverage_problems,
    generate_key,
    key_to_pem,
    load_server_key,
    san_for_hosts,
    thumbprint,
    uacell_name,
)

_log = logging.getLogger(__name__)


class InstallRefused(ValueError):
    """The certificate cannot be the server's; the message says why, ``code`` is the OPC UA status code's
    name that says it to a client (OPC 10000-12 UpdateCertificate)."""

    def __init__(self, message: str, code: str = "BadCertificateInvalid") -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Installed:
    certificate: x509.Certificate
    issuers: tuple[x509.Certificate, ...]
    new_key: bool  # the pending key became the server's key
    warnings: tuple[str, ...]  # installed, but worth saying (it expires soon)


def signing_request(
    paths: PkiPaths,
    application_uri: str,
    hosts: Iterable[str],
    *,
    new_key: bool = False,
    subject: x509.Name | None = None,
) -> bytes:
    """A PEM certificate signing request for the server's key (``new_key``: for a new key, kept in
    ``pki/own/pending/key.pem`` until ``install_certificate`` takes its certificate), for ``subject`` (by
    default the current certificate's)."""
    if new_key:
        key = generate_key()
        atomic_write(paths.pending_key, key_to_pem(key), mode=0o600)
        paths.pending_key.parent.chmod(0o700)
    elif paths.key.exists():
        key = load_server_key(paths)
    else:
        raise InstallRefused(
            f"{paths.key} does not exist: start the server once, or ask for a new key", "BadInvalidState"
        )
    dns, ips = san_for_hosts(hosts)
    subject = subject or _current_subject(paths)
    request = (
        x509.CertificateSigningRequestBuilder()
        .subject_name(subject)
        .add_extension(application_names(application_uri, dns, ips), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(application_key_usage(sign_certificates=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .sign(key, hashes.SHA256())
    )
    return request.public_bytes(serialization.Encoding.PEM)


def _current_subject(paths: PkiPaths) -> x509.Name:
    try:
        return x509.load_der_x509_certificate(paths.cert.read_bytes()).subject
    except (OSError, ValueError):
        return uacell_name()


def read_certificates(data: bytes) -> list[x509.Certificate]:
    """The certificates of a file: PEM blocks, or DER certificates appended. ValueError if none."""
    if b"-----BEGIN" in data:
        return x509.load_pem_x509_certificates(data)
    return split_chain(data)


def install_certificate(
    paths: PkiPaths,
    data: bytes,
    application_uri: str,
    hosts: Iterable[str],
    *,
    now: dt.datetime | None = None,
    private_key: rsa.RSAPrivateKey | None = None,
) -> Installed:
    """Make the certificate in ``data`` (its issuers after it) the server's; InstallRefused, with
    nothing changed, when it cannot be (the module's text lists the checks). ``private_key``: the
    certificate's key, made outside the server (OPC 10000-12 UpdateCertificate), which becomes the
    server's with it."""
    now = now or dt.datetime.now(dt.UTC)
    try:
        certs = read_certificates(data)
    except ValueError as exc:
        raise InstallRefused(f"not a certificate file: {exc}") from None
    leaf, issuers = certs[0], tuple(certs[1:])
    if private_key is None:
        new_key = _key_of(paths, leaf)
    elif private_key.public_key().public_numbers() != _rsa_public(leaf).public_numbers():
        raise InstallRefused("the private key given is not the certificate's", "BadSecurityChecksFailed")
    else:
        new_key = True
    _check_usable(leaf, application_uri, hosts, now)
    problem = chain_problem(leaf, issuers)
    if problem:
        raise InstallRefused(problem, "BadSecurityChecksFailed")
    warnings = []
    if leaf.not_valid_after_utc - RENEW_BEFORE < now:
        warnings.append(f"it expires on {leaf.not_valid_after_utc:%Y-%m-%d}: ask the CA for the next one soon")
    back_up(paths, move=False, now=now)
    if private_key is not None:
        atomic_write(paths.pending_key, key_to_pem(private_key), mode=0o600)
    if issuers:
        atomic_write(paths.chain, b"".join(c.public_bytes(serialization.Encoding.PEM) for c in issuers), mode=0o644)
    else:
        paths.chain.unlink(missing_ok=True)
    atomic_write(paths.cert, der_of(leaf), mode=0o644)
    if new_key:
        finish_install(paths)
    return Installed(leaf, issuers, new_key, tuple(warnings))


def _rsa_public(leaf: x509.Certificate) -> rsa.RSAPublicKey:
    public = leaf.public_key()
    if not isinstance(public, rsa.RSAPublicKey):
        raise InstallRefused("its key is not an RSA key")
    return public


def _key_of(paths: PkiPaths, leaf: x509.Certificate) -> bool:
    """Is ``leaf`` the certificate of the pending key (True) or of the server's key (False)?"""
    public = _rsa_public(leaf)
    for path, pending in ((paths.pending_key, True), (paths.key, False)):
        if path.exists() and _public_numbers(path) == public.public_numbers():
            return pending
    raise InstallRefused(
        f"it is not the certificate of the server's key nor of a pending one (thumbprint "
        f"{thumbprint(der_of(leaf))}): the CA must sign a request made by `uacell cert request`",
        "BadSecurityChecksFailed",
    )


def _public_numbers(path: Path) -> rsa.RSAPublicNumbers | None:
    key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    return key.public_key().public_numbers() if isinstance(key, rsa.RSAPrivateKey) else None


def _check_usable(leaf: x509.Certificate, application_uri: str, hosts: Iterable[str], now: dt.datetime) -> None:
    if now < leaf.not_valid_before_utc:
        raise InstallRefused(
            f"it is not valid before {leaf.not_valid_before_utc:%Y-%m-%d %H:%M} UTC", "BadCertificateTimeInvalid"
        )
    if now > leaf.not_valid_after_utc:
        raise InstallRefused(f"it expired on {leaf.not_valid_after_utc:%Y-%m-%d}", "BadCertificateTimeInvalid")
    problems = [p for p in coverage_problems(leaf, application_uri, hosts) if not p.startswith("expires")]
    problems += usage_problems(leaf)
    if problems:
        code = (
            "BadCertificateUriInvalid"
            if any(p.startswith("application URI") for p in problems)
            else "BadCertificateHostNameInvalid"
            if any(p.startswith(("host name", "address")) for p in problems)
            else "BadCertificateUseNotAllowed"
        )
        raise InstallRefused("it does not suit this server: " + "; ".join(problems), code)


def usage_problems(cert: x509.Certificate) -> list[str]:
    """What the certificate's key usages forbid of a server's certificate (signing, key encipherment;
    serverAuth when it names extended usages at all)."""
    problems = []
    try:
        usage = cert.extensions.get_extension_for_class(x509.KeyUsage).value
    except x509.ExtensionNotFound:
        pass
    else:
        if not usage.digital_signature:
            problems.append("its key usage does not allow digitalSignature")
        if not usage.key_encipherment:
            problems.append("its key usage does not allow keyEncipherment")
    try:
        extended = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    except x509.ExtensionNotFound:
        pass
    else:
        if ExtendedKeyUsageOID.SERVER_AUTH not in extended:
            problems.append("its extended key usage does not allow serverAuth")
    return problems


def chain_problem(leaf: x509.Certificate, issuers: Sequence[x509.Certificate]) -> str:
    """Why ``issuers`` is not the chain of ``leaf`` (each certificate issued by the next, each a CA);
    "" when it is."""
    below = leaf
    for n, issuer in enumerate(issuers, 1):
        if not issued_by(below, issuer):
            return f"certificate {n + 1} of the file did not issue certificate {n} (the CA's follow in order)"
        if not may_sign_certificates(issuer):
            return f"certificate {n + 1} of the file is not a CA's certificate that may sign certificates"
        below = issuer
    return ""


def own_issuers(paths: PkiPaths, leaf: x509.Certificate) -> list[x509.Certificate]:
    """The CA certificates to send after the server's (``pki/own/chain.pem``), when they are its chain."""
    try:
        issuers = read_certificates(paths.chain.read_bytes())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:
        _log.warning("%s cannot be read (%s): the server's certificate is sent without its CA's", paths.chain, exc)
        return []
    problem = chain_problem(leaf, issuers)
    if problem:
        _log.warning("%s is not the chain of the server's certificate (%s): not sent", paths.chain, problem)
        return []
    return issuers


def finish_install(paths: PkiPaths) -> bool:
    """The pending key becomes the server's key when ``cert.der`` is its certificate (an install, or one
    a crash cut short after writing the certificate); True when it did."""
    if not (paths.pending_key.exists() and paths.cert.exists()):
        return False
    try:
        public = x509.load_der_x509_certificate(paths.cert.read_bytes()).public_key()
        pending = _public_numbers(paths.pending_key)
    except ValueError:
        return False
    if not isinstance(public, rsa.RSAPublicKey) or pending != public.public_numbers():
        return False
    data = paths.pending_key.read_bytes()
    atomic_write(paths.key, data, mode=0o600)
    paths.key_checked.unlink(missing_ok=True)  # checked once at the next start (pki.load_server_key)
    paths.pending_key.unlink()
    return True
