"""The server's certificate and the trust list for client certificates, under ``<data_dir>/pki/``.

``pki/own/cert.der`` + ``pki/own/key.pem``   the application instance certificate and its key, made on
                                            first start, remade (old pair kept in ``own/backup/``)
                                            when the application URI or listening hosts change
``pki/trusted/``                            certificates the server trusts (DER or PEM): clients', or CAs'
                                            whose every certificate is trusted
``pki/issuers/``                            CA certificates that complete chains, not trusted themselves
``pki/crl/``                                revocation lists of the CAs (``.crl``, DER or PEM)
``pki/rejected/``                           refused client certificates, ``<thumbprint>.der``;
                                            ``uacell cert trust`` (or moving one to trusted/) trusts it
                                            (capped in count and age: ``prune_rejected``)

``CertificateValidator`` decides on a client's certificate chain at CreateSession (``uacell.security.chain``
for the chain's steps).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import hashlib
import ipaddress
import logging
import os
import shutil
import socket
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from asyncua import ua
from asyncua.common.utils import ServiceError
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from uacell.core.files import atomic_write
from uacell.security.chain import Anchors, Refusal, check_chain, is_self_signed, split_chain

_log = logging.getLogger(__name__)

KEY_SIZE = 2048
VALIDITY_DAYS = 5 * 365
RENEW_BEFORE = dt.timedelta(days=30)  # remake a certificate this close to its end
CERT_SUFFIXES = {".der", ".cer", ".crt", ".pem"}
CRL_SUFFIXES = {".crl"}

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
_T = TypeVar("_T")


@dataclass(frozen=True)
class PkiPaths:
    """Where the PKI files live for one data directory."""

    root: Path

    @classmethod
    def in_data_dir(cls, data_dir: Path) -> PkiPaths:
        return cls(Path(data_dir) / "pki")

    @property
    def own(self) -> Path:
        return self.root / "own"

    @property
    def cert(self) -> Path:
        return self.own / "cert.der"

    @property
    def key(self) -> Path:
        return self.own / "key.pem"

    @property
    def key_checked(self) -> Path:
        """The SHA-256 of the key file whose RSA consistency was checked (``load_server_key``)."""
        return self.own / "key.checked"

    @property
    def backup(self) -> Path:
        return self.own / "backup"

    @property
    def chain(self) -> Path:
        """The certificates of the CA that issued the server's certificate, sent after it (decision 95)."""
        return self.own / "chain.pem"

    @property
    def pending_key(self) -> Path:
        """A key made by ``uacell cert request --new-key``, waiting for its certificate."""
        return self.own / "pending" / "key.pem"

    @property
    def trusted(self) -> Path:
        return self.root / "trusted"

    @property
    def rejected(self) -> Path:
        return self.root / "rejected"

    @property
    def issuers(self) -> Path:
        return self.root / "issuers"

    @property
    def crl(self) -> Path:
        return self.root / "crl"

    @property
    def trust_update(self) -> Path:
        """A replacement of the trust list being written (``uacell.security.trust_list_file``)."""
        return self.root / "trust-update"

    def create(self) -> None:
        for d in (self.own, self.trusted, self.rejected, self.issuers, self.crl):
            d.mkdir(parents=True, exist_ok=True)
        self.own.chmod(0o700)


# Certificates -----------------------------------------------------------------------------------------


def generate_key(size: int = KEY_SIZE) -> rsa.RSAPrivateKey:
    return rsa.generate_private_key(public_exponent=65537, key_size=size)


def make_certificate(
    key: rsa.RSAPrivateKey,
    application_uri: str,
    *,
    common_name: str | None = None,
    dns_names: Iterable[str] = (),
    ip_addresses: Iterable[IPAddress] = (),
    server: bool = True,
    client: bool = True,
    days: int = VALIDITY_DAYS,
    not_before: dt.datetime | None = None,
) -> x509.Certificate:
    """A self-signed OPC UA application instance certificate (OPC 10000-6, 6.2.2), SHA-256 signed."""
    name = uacell_name(common_name)
    start = (not_before or dt.datetime.now(dt.UTC)) - dt.timedelta(minutes=5)  # tolerate clock skew
    usages = [ExtendedKeyUsageOID.SERVER_AUTH] if server else []
    usages += [ExtendedKeyUsageOID.CLIENT_AUTH] if client else []
    public = key.public_key()
    builder = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
        .add_extension(application_names(application_uri, dns_names, ip_addresses), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)  # self-signed
        .add_extension(application_key_usage(sign_certificates=True), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(public), critical=False)
    )
    return builder.sign(key, hashes.SHA256())


def uacell_name(common_name: str | None = None) -> x509.Name:
    """The subject uacell gives its own certificates (``uacell@<host>`` unless named otherwise)."""
    return x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, common_name or f"uacell@{socket.gethostname()}"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "uacell"),
        ]
    )


def application_names(
    application_uri: str, dns_names: Iterable[str], ip_addresses: Iterable[IPAddress]
) -> x509.SubjectAlternativeName:
    """An Application Instance Certificate's subjectAltName (OPC 10000-6 6.2.2): the URI, then the host
    names and addresses."""
    san: list[x509.GeneralName] = [x509.UniformResourceIdentifier(application_uri)]
    san += [x509.DNSName(d) for d in dict.fromkeys(dns_names)]
    san += [x509.IPAddress(i) for i in dict.fromkeys(ip_addresses)]
    return x509.SubjectAlternativeName(san)


def revocation_lists(paths: PkiPaths) -> list[tuple[Path, x509.CertificateRevocationList]]:
    """The readable revocation lists in ``pki/crl/`` with their files."""
    found = []
    if paths.crl.is_dir():
        for f in sorted(paths.crl.iterdir()):
            if f.is_file() and f.suffix.lower() in CRL_SUFFIXES:
                try:
                    found.append((f, load_crl(f.read_bytes())))
                except (OSError, ValueError):
                    continue
    return found


def application_key_usage(*, sign_certificates: bool) -> x509.KeyUsage:
    """The key usages OPC 10000-6 6.2.2 gives an Application Instance Certificate (a self-signed one also
    signs certificates: itself)."""
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=True,
        key_encipherment=True,
        data_encipherment=True,
        key_agreement=False,
        key_cert_sign=sign_certificates,
        crl_sign=False,
        encipher_only=False,
        decipher_only=False,
    )


def back_up(paths: PkiPaths, *, move: bool, now: dt.datetime | None = None) -> None:
    """The server's certificate, key and CA chain into ``pki/own/backup/`` under the time (moved, or
    copied when the files stay in use until their successors are written)."""
    stamp = (now or dt.datetime.now(dt.UTC)).strftime("%Y%m%dT%H%M%SZ")
    paths.backup.mkdir(parents=True, exist_ok=True)
    for f, name in (
        (paths.cert, f"cert-{stamp}.der"),
        (paths.key, f"key-{stamp}.pem"),
        (paths.chain, f"chain-{stamp}.pem"),
    ):
        if f.exists():
            (shutil.move if move else shutil.copy2)(f, paths.backup / name)


def key_to_pem(key: rsa.RSAPrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def cert_to_der(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.DER)


def make_client_certificate(
    application_uri: str,
    *,
    key: rsa.RSAPrivateKey | None = None,
    common_name: str = "uacell test client",
    days: int = 365,
    not_before: dt.datetime | None = None,
) -> tuple[bytes, bytes]:
    """A client certificate and key for tests and tools: (certificate DER, private key PEM)."""
    key = key or generate_key()
    cert = make_certificate(
        key,
        application_uri,
        common_name=common_name,
        dns_names=[socket.gethostname()],
        server=False,
        client=True,
        days=days,
        not_before=not_before,
    )
    return cert_to_der(cert), key_to_pem(key)


def san_for_hosts(hosts: Iterable[str]) -> tuple[list[str], list[IPAddress]]:
    """DNS names and IP addresses for the certificate of a server listening on ``hosts``.

    A wildcard address (0.0.0.0, ::) stands for this machine: its host name, FQDN and their addresses.
    """
    dns: list[str] = []
    ips: list[IPAddress] = []
    for host in hosts:
        h = host.strip().strip("[]")
        try:
            ip = ipaddress.ip_address(h)
        except ValueError:
            dns.append(h)
            if h.lower() == "localhost":
                ips.append(ipaddress.ip_address("127.0.0.1"))
            continue
        if ip.is_unspecified:
            names = [socket.gethostname(), socket.getfqdn()]
            dns += names
            for n in names:
                ips += _resolve(n)
        else:
            ips.append(ip)
            if ip.is_loopback:
                dns.append("localhost")
    return list(dict.fromkeys(dns)), list(dict.fromkeys(ips))


def _resolve(name: str) -> list[IPAddress]:
    try:
        infos = socket.getaddrinfo(name, None, proto=socket.IPPROTO_TCP)
    except OSError:
        return []
    return [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]


def _required_for_hosts(hosts: Iterable[str]) -> tuple[set[str], set[IPAddress]]:
    """What a certificate must cover: the listening hosts as given (not what a wildcard resolves to)."""
    dns: set[str] = set()
    ips: set[IPAddress] = set()
    for host in hosts:
        h = host.strip().strip("[]")
        try:
            ip = ipaddress.ip_address(h)
        except ValueError:
            dns.add(h.lower())
            continue
        if ip.is_unspecified:
            dns.add(socket.gethostname().lower())
        else:
            ips.add(ip)
    return dns, ips


def coverage_problems(cert: x509.Certificate, application_uri: str, hosts: Iterable[str]) -> list[str]:
    """Why ``cert`` does not suit a server with this URI listening on ``hosts`` (empty when it does)."""
    problems = []
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return ["no subjectAltName"]
    if application_uri not in san.get_values_for_type(x509.UniformResourceIdentifier):
        problems.append(f"application URI {application_uri} missing")
    have_dns = {d.lower() for d in san.get_values_for_type(x509.DNSName)}
    have_ips = set(san.get_values_for_type(x509.IPAddress))
    need_dns, need_ips = _required_for_hosts(hosts)
    problems += [f"host name {d} missing" for d in sorted(need_dns - have_dns)]
    problems += [f"address {i} missing" for i in sorted(need_ips - have_ips, key=str)]
    public = cert.public_key()
    if not isinstance(public, rsa.RSAPublicKey) or public.key_size < KEY_SIZE:
        problems.append(f"not an RSA key of {KEY_SIZE} bits or more")
    if cert.not_valid_after_utc - RENEW_BEFORE < dt.datetime.now(dt.UTC):
        problems.append(f"expires {cert.not_valid_after_utc:%Y-%m-%d}")
    return problems


def ensure_server_certificate(
    paths: PkiPaths,
    application_uri: str,
    hosts: Iterable[str],
    *,
    key: rsa.RSAPrivateKey | None = None,
) -> tuple[Path, Path]:
    """Create (or reuse, or remake) the server certificate; returns (cert path, key path).

    The paths can go straight to asyncua's ``Server.load_certificate`` / ``load_private_key``.
    ``key`` is for tests; normally a fresh key is generated.
    """
    hosts = list(hosts)
    paths.create()
    if paths.cert.exists() and paths.key.exists():
        try:
            cert = x509.load_der_x509_certificate(paths.cert.read_bytes())
            problems = coverage_problems(cert, application_uri, hosts)
        except ValueError as exc:
            problems = [f"unreadable ({exc})"]
        if not problems:
            return paths.cert, paths.key
        if not problems[0].startswith("unreadable") and not is_self_signed(cert):
            # a CA issued it (decision 95): a self-signed one in its place would lock out every client that
            # trusts the CA, so it is kept, and the log says at every start what the CA must issue anew
            _log.warning(
                "the server certificate %s from %s no longer fits (%s): it is kept; make a request for the "
                "next one with `uacell cert request` and install what the CA issues with `uacell cert install`",
                thumbprint(cert_to_der(cert)),
                cert.issuer.rfc4514_string(),
                "; ".join(problems),
            )
            return paths.cert, paths.key
        back_up(paths, move=True)
        _log.warning(
            "server certificate no longer fits (%s): made a new one, old one kept in %s",
            "; ".join(problems),
            paths.backup,
        )
    dns, ips = san_for_hosts(hosts)
    key = key or generate_key()
    cert = make_certificate(key, application_uri, dns_names=dns, ip_addresses=ips)
    pem = key_to_pem(key)
    atomic_write(paths.key, pem, mode=0o600)
    atomic_write(paths.key_checked, _digest(pem).encode(), mode=0o600)  # made here: consistent
    atomic_write(paths.cert, cert_to_der(cert), mode=0o644)
    _log.info(
        "created server certificate %s (thumbprint %s) for %s",
        paths.cert,
        thumbprint(cert_to_der(cert)),
        ", ".join([application_uri, *dns, *map(str, ips)]),
    )
    return paths.cert, paths.key


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def load_server_key(paths: PkiPaths) -> rsa.RSAPrivateKey:
    """The server's private key from ``paths.key``. The RSA consistency check cryptography makes on
    loading (about 30 ms for 2048 bits, a tenth of a restart) runs once per key: a key uacell made, or
    one that passed the check, has its file's SHA-256 in ``paths.key_checked``, and a key file with
    that digest is loaded without it. A key put there by hand, or changed, is checked."""
    data = paths.key.read_bytes()
    digest = _digest(data)
    try:
        known = paths.key_checked.read_text().strip() == digest
    except OSError:
        known = False
    key = serialization.load_pem_private_key(data, password=None, unsafe_skip_rsa_key_validation=known)
    if not isinstance(key, rsa.RSAPrivateKey):
        raise ValueError(f"{paths.key} is not an RSA private key")
    if not known:
        try:
            atomic_write(paths.key_checked, digest.encode(), mode=0o600)
        except OSError as exc:  # checked again next time; nothing else depends on the note
            _log.warning("cannot note that %s was checked (%s): it is checked at every start", paths.key, exc)
    return key


# Trust list -------------------------------------------------------------------------------------------


def thumbprint(der: bytes) -> str:
    """The OPC UA certificate thumbprint (SHA-1 of the DER), hex."""
    return hashlib.sha1(der).hexdigest()  # the thumbprint is defined as SHA-1


def load_any_certificate(data: bytes) -> x509.Certificate:
    if data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data)
    return x509.load_der_x509_certificate(data)


def certificate_file_name(der: bytes) -> str:
    """A certificate's file in trusted/, issuers/ or rejected/: by thumbprint alone (no spaces or
    brackets, so a path from the log can be pasted into a shell)."""
    return f"{thumbprint(der)}.der"


def crl_file_name(crl: x509.CertificateRevocationList) -> str:
    """A revocation list's file in crl/: one per CA, by the SHA-1 of its issuer's name."""
    return f"{hashlib.sha1(crl.issuer.public_bytes()).hexdigest()}.crl"


@dataclass(frozen=True)
class RejectedLimit:
    """How many refused certificates ``pki/rejected/`` keeps, and for how long (seconds)."""

    max_files: int = 100
    max_age: float = 30 * 86400.0


def prune_rejected(directory: Path, limit: RejectedLimit, now: float | None = None) -> list[Path]:
    """Delete certificates in ``directory`` older than ``limit.max_age``, then the oldest beyond
    ``limit.max_files``; returns the files deleted, oldest first. Age is the file's modification time."""
    now = time.time() if now is None else now
    files = []
    for f in directory.iterdir():
        if f.suffix.lower() in CERT_SUFFIXES and f.is_file():
            try:
                files.append((f.stat().st_mtime, f.name, f))
            except OSError:  # removed meanwhile
                continue
    files.sort()
    doomed = [f for mtime, _, f in files if now - mtime > limit.max_age]
    kept = [f for mtime, _, f in files if now - mtime <= limit.max_age]
    doomed += kept[: max(0, len(kept) - limit.max_files)]
    for f in doomed:
        f.unlink(missing_ok=True)
    return doomed


class TrustList:
    """Decides on client certificates from the files under ``pki/``: trusted/, issuers/, crl/
    (read at every check: operators add files while the server runs, and sessions are rare).

    A chain is checked as ``uacell.security.chain.check_chain`` says. With ``trust_on_first_use``, a
    certificate refused only because nothing trusts it is copied to trusted/ and accepted; otherwise a
    certificate that trusting it would let in is written to rejected/, and the log says how to trust it.
    """

    def __init__(
        self,
        paths: PkiPaths,
        *,
        trust_on_first_use: bool = False,
        require_revocation_lists: bool = True,
        rejected_limit: RejectedLimit | None = None,
        report_refusal: Callable[[str, str], object] | None = None,
    ) -> None:
        self.paths = paths
        self.trust_on_first_use = trust_on_first_use
        self.require_revocation_lists = require_revocation_lists
        self.rejected_limit = rejected_limit or RejectedLimit()
        # How refusals are logged: (message, reason), the server rate-limits them per client address and
        # reason (the status code's name); default: a warning each.
        self.report_refusal: Callable[[str, str], object] = report_refusal or _warn
        self._pruning_logged = False
        paths.create()
        self.prune_rejected()

    def prune_rejected(self) -> list[Path]:
        """Keep ``pki/rejected/`` within its limit (oldest dropped first); the first drop is logged."""
        dropped = prune_rejected(self.paths.rejected, self.rejected_limit)
        if dropped and not self._pruning_logged:
            self._pruning_logged = True
            limit = self.rejected_limit
            _log.warning(
                "%s keeps at most %d refused certificates for %.0f days: dropped the oldest (%s); "
                "further drops are not logged",
                self.paths.rejected,
                limit.max_files,
                limit.max_age / 86400,
                ", ".join(f.name for f in dropped),
            )
        return dropped

    def anchors(self) -> Anchors:
        """The trusted and issuer certificates and the revocation lists, as the files are now."""
        return read_anchors(self.paths)

    def is_trusted(self, der: bytes) -> bool:
        """Is this exact certificate in trusted/?"""
        return self.anchors().is_trusted(x509.load_der_x509_certificate(der))

    def trust(self, der: bytes) -> Path:
        """Put ``der`` into trusted/ (and out of rejected/); returns its file."""
        x509.load_der_x509_certificate(der)  # ValueError for what is no DER certificate
        target = self.paths.trusted / certificate_file_name(der)
        atomic_write(target, der, mode=0o644)
        (self.paths.rejected / target.name).unlink(missing_ok=True)
        return target

    def reject(self, der: bytes) -> Path:
        """Put ``der`` into rejected/ so an operator can trust it by moving the file."""
        x509.load_der_x509_certificate(der)  # ValueError for what is no DER certificate
        target = self.paths.rejected / certificate_file_name(der)
        if not target.exists():
            atomic_write(target, der, mode=0o644)
            self.prune_rejected()
        return target

    def admit(self, chain: bytes | Sequence[x509.Certificate], application_uri: str = "") -> bool:
        """Decide on a client certificate (DER, or a chain): trusted, trusted now on first use, or refused."""
        return self.refusal(chain, application_uri) is None

    def refusal(self, chain: bytes | Sequence[x509.Certificate], application_uri: str = "") -> Refusal | None:
        """Why the chain (its DER, or its certificates, the client's first) is refused, logged with what
        to do about it; None when it is trusted (on first use, too)."""
        certs = split_chain(chain) if isinstance(chain, bytes) else list(chain)
        anchors = self.anchors()
        now = dt.datetime.now(dt.UTC)
        refusal = check_chain(certs, anchors, now, require_crls=self.require_revocation_lists)
        if refusal is None:
            return None
        der = cert_to_der(certs[0])
        who = f" of {application_uri}" if application_uri else ""
        stem = f"refused client certificate{who} (thumbprint {thumbprint(der)})"
        if refusal.code in _TRUSTING_HELPS:
            pinned = dataclasses.replace(anchors, trusted=(*anchors.trusted, certs[0]))
            alone = check_chain(certs, pinned, now, require_crls=self.require_revocation_lists)
            if alone is not None:  # trusting it would not let it in: say why, offer nothing
                self.report_refusal(
                    f"{stem}: {refusal.why}; and trusting it would not help: {self._said(alone)}", alone.name
                )
                return refusal
            if self.trust_on_first_use:
                path = self.trust(der)
                _log.warning("trusting client certificate%s on first use: %s (delete it to revoke)", who, path)
                return None
            path = self.reject(der)
            to_trust = (
                f"To trust it, move {path} to {self.paths.trusted}/ "
                f"(or run: uacell cert trust {thumbprint(der)[:12]} --data-dir {self.paths.root.parent})"
            )
            if refusal.code == ua.StatusCodes.BadCertificateUntrusted:
                self.report_refusal(
                    f"refused untrusted client certificate{who} (thumbprint {thumbprint(der)}). {to_trust}",
                    refusal.name,
                )
            else:
                self.report_refusal(
                    f"{stem}: {self._said(refusal)} Put its CA's certificate into {self.paths.issuers}/ (or into "
                    f"{self.paths.trusted}/ to trust every certificate it issues) and the CA's revocation list into "
                    f"{self.paths.crl}/; or trust this certificate by itself. {to_trust}",
                    refusal.name,
                )
            return refusal
        self.report_refusal(f"{stem}: {self._said(refusal)}", refusal.name)
        return refusal

    def _said(self, refusal: Refusal) -> str:
        """A refusal in words for the log, with what to do where that is one file."""
        hint = ""
        if refusal.code in _REVOCATION_UNKNOWN:
            hint = f" Put the CA's revocation list into {self.paths.crl}/ (uacell cert crl FILE)."
        return f"{refusal.why} ({refusal.name}).{hint}"


# Refusals that trusting the client's certificate by itself would lift: it goes to rejected/.
_TRUSTING_HELPS = {ua.StatusCodes.BadCertificateUntrusted, ua.StatusCodes.BadCertificateChainIncomplete}
_REVOCATION_UNKNOWN = {
    ua.StatusCodes.BadCertificateRevocationUnknown,
    ua.StatusCodes.BadCertificateIssuerRevocationUnknown,
}
# What a client is told (OPC 10000-4 6.1.3, decision 92): its own certificate's period, URI and trust
# as before, and what the security policy finds wrong with it (decision 101); a failure in its chain
# (an issuer, a signature, a revocation, an issuer's policy) as Bad_SecurityChecksFailed.
_TOLD = {
    ua.StatusCodes.BadCertificateUntrusted,
    ua.StatusCodes.BadCertificateTimeInvalid,
    ua.StatusCodes.BadCertificateUriInvalid,
}
_TOLD_OF_ITS_OWN = {ua.StatusCodes.BadCertificatePolicyCheckFailed}


def told(code: int, *, own: bool = False) -> int:
    """The status a refused client is told for a refusal's ``code`` (``own``: about the client's own
    certificate, not an issuer of it)."""
    if code in _TOLD or (own and code in _TOLD_OF_ITS_OWN):
        return code
    return int(ua.StatusCodes.BadSecurityChecksFailed)


def load_crl(data: bytes) -> x509.CertificateRevocationList:
    """A revocation list from DER or PEM; ValueError when it is none."""
    if data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_crl(data)
    return x509.load_der_x509_crl(data)


def read_anchors(paths: PkiPaths) -> Anchors:
    """The trusted and issuer certificates and the revocation lists, as the files under ``paths`` are
    now (a file that does not load is left out, with a warning)."""
    return Anchors(
        tuple(_read_files(paths.trusted, CERT_SUFFIXES, load_any_certificate, "the trust list")),
        tuple(_read_files(paths.issuers, CERT_SUFFIXES, load_any_certificate, "the issuer list")),
        tuple(_read_files(paths.crl, CRL_SUFFIXES, load_crl, "the revocation lists")),
    )


TrustStamp = tuple[tuple[str, str, int, int], ...]


def trust_stamp(paths: PkiPaths) -> TrustStamp:
    """What ``read_anchors`` would read, cheaply told apart: each file of trusted/, issuers/ and crl/
    with its modification time and size. Another stamp means the files changed (``uacell cert``, a
    GDS, an operator's copy)."""
    entries: list[tuple[str, str, int, int]] = []
    for folder in (paths.trusted, paths.issuers, paths.crl):
        try:
            with os.scandir(folder) as found:
                for entry in found:
                    with contextlib.suppress(OSError):  # removed meanwhile: the next look sees it gone
                        st = entry.stat()
                        entries.append((folder.name, entry.name, st.st_mtime_ns, st.st_size))
        except OSError:
            continue  # no folder: nothing in it
    return tuple(sorted(entries))


def _read_files(folder: Path, suffixes: set[str], load: Callable[[bytes], _T], what: str) -> list[_T]:
    found: list[_T] = []
    if not folder.is_dir():
        return found
    for f in sorted(folder.iterdir()):
        if f.suffix.lower() not in suffixes or not f.is_file():
            continue
        try:
            found.append(load(f.read_bytes()))
        except (ValueError, OSError) as exc:
            _log.warning("ignoring %s in %s: %s", f, what, exc)
    return found


@dataclass(frozen=True)
class CertificateVerdict:
    """A refused client certificate: ``told`` is what the client is told, ``precise`` the step's own
    code (for the log and the audit events), ``certificate`` the client's DER, ``why`` in words."""

    told: int
    precise: int
    certificate: bytes
    why: str


def _warn(message: str, reason: str) -> None:
    _log.warning("%s", message)


class CertificateValidator:
    """A client's certificate chain: the client certificate's validity period and (at CreateSession,
    where the client names it) its ApplicationUri, then its chain and the trust list
    (``TrustList.refusal``). The client certificate is checked first so that trust on first use never
    records an expired or mismatched certificate.

    As a callable it also fits asyncua's ``Server.set_certificate_validator`` (the client certificate
    alone; raises ``ServiceError`` with the code the client is told).
    """

    def __init__(self, trust_list: TrustList) -> None:
        self.trust_list = trust_list

    async def __call__(self, cert: x509.Certificate, app_description: ua.ApplicationDescription) -> None:
        verdict = self.check([cert], app_description.ApplicationUri or "")
        if verdict is not None:
            raise ServiceError(verdict.told)

    def check(self, chain: Sequence[x509.Certificate], application_uri: str) -> CertificateVerdict | None:
        """None when the chain (the client's certificate first) is trusted for ``application_uri`` (the
        one the client names); else why not."""
        der = cert_to_der(chain[0])
        code = _own_problem(chain[0], application_uri, dt.datetime.now(dt.UTC))
        if code is not None:
            name = ua.StatusCode(code).name
            self.trust_list.report_refusal(
                f"refused client certificate {thumbprint(der)} of {application_uri}: {name}", name
            )
            return CertificateVerdict(code, code, der, f"the client certificate: {name}")
        refusal = self.trust_list.refusal(chain, application_uri)
        if refusal is None:
            return None
        own = refusal.certificate == chain[0]
        return CertificateVerdict(told(refusal.code, own=own), refusal.code, der, refusal.why)


def _own_problem(cert: x509.Certificate, application_uri: str, now: dt.datetime) -> int | None:
    """OPC 10000-4 6.1.3's Validity Period and URI steps for the client's own certificate."""
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        return int(ua.StatusCodes.BadCertificateTimeInvalid)
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return int(ua.StatusCodes.BadCertificateInvalid)
    if application_uri not in san.get_values_for_type(x509.UniformResourceIdentifier):
        return int(ua.StatusCodes.BadCertificateUriInvalid)
    return None
