"""Whether a client's certificate chain is trusted: OPC 10000-4 6.1.3 and OPC 10000-6 6.2.6, pure.

A client may send its Application Instance Certificate alone or followed by its issuers (the DER
encodings appended, the end certificate first: ``split_chain``). ``check_chain`` builds the chain
from the end certificate to a self-signed root, taking issuers from what the client sent and from the
administrator's lists (``Anchors``: trusted certificates, issuer certificates, revocation lists), and
answers the first step of OPC 10000-4's validation table that fails, with its status code, or None:

1. build the chain: an issuer is found by name and its key verifies the signature
   (Bad_CertificateChainIncomplete when none is found; Bad_CertificateInvalid when a signature,
   a root's own included, does not verify);
   the Security Policy check (``policy_problem``, decision 101), made on the end certificate before
   the chain is built and on each issuer as it is found: every certificate signed with SHA-256 or a
   longer hash, an application's key RSA of 2048 to 4096 bits (Bad_CertificatePolicyCheckFailed);
2. the trust list: the certificate or one of its issuers is a trusted certificate
   (Bad_CertificateUntrusted);
3. validity: each issuer is valid now (Bad_CertificateIssuerTimeInvalid; the end certificate's own
   period is checked before, with its URI, by the caller);
4. usage: each issuer is a CA allowed to sign certificates (Bad_CertificateIssuerUseNotAllowed);
5. revocation: every issuer has a revocation list signed by it whose nextUpdate has not passed
   (Bad_CertificateRevocationUnknown for the end certificate's issuer,
   Bad_CertificateIssuerRevocationUnknown above it, unless ``require_crls`` is off; decision 98), and
   no certificate of the chain is on its issuer's newest list, stale or not (Bad_CertificateRevoked,
   Bad_CertificateIssuerRevoked).

A certificate the administrator trusts by itself, whose issuer is nowhere to be found, is trusted as it
was before chains were checked (decision 92): trusting it is the decision, as pinning a key is. Once
its issuer is known, the whole chain is checked, but a missing revocation list does not refuse it (a
list that is there does).
"""

from __future__ import annotations

import datetime as dt
import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from asyncua import ua
from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import SignatureAlgorithmOID

_S = ua.StatusCodes
MAX_DEPTH = 8  # certificates in a chain, the end certificate and the root included
# OPC 10000-7, the policies uacell offers (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss):
# certificates signed with RSA over a hash of 256 bits or more, application keys of 2048 to 4096 bits
POLICY_SIGNATURES = {
    SignatureAlgorithmOID.RSA_WITH_SHA256,
    SignatureAlgorithmOID.RSA_WITH_SHA384,
    SignatureAlgorithmOID.RSA_WITH_SHA512,
    SignatureAlgorithmOID.RSASSA_PSS,
}
POLICY_HASHES = (hashes.SHA256, hashes.SHA384, hashes.SHA512)
MIN_KEY_BITS, MAX_KEY_BITS = 2048, 4096


@dataclass(frozen=True)
class Refusal:
    """Why a chain is not trusted: the step's status code, the certificate it failed for, in words."""

    code: int
    certificate: x509.Certificate
    why: str

    @property
    def name(self) -> str:
        return str(ua.StatusCode(self.code).name)


@dataclass(frozen=True)
class Anchors:
    """What the administrator provides: trusted certificates (applications or CAs), issuer certificates
    (CAs that complete chains without being trusted themselves), revocation lists of CAs."""

    trusted: tuple[x509.Certificate, ...] = ()
    issuers: tuple[x509.Certificate, ...] = ()
    crls: tuple[x509.CertificateRevocationList, ...] = ()

    def is_trusted(self, cert: x509.Certificate) -> bool:
        der = der_of(cert)
        return any(der_of(t) == der for t in self.trusted)


def der_of(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.DER)


def split_chain(data: bytes) -> list[x509.Certificate]:
    """The certificates of a ByteString holding one DER certificate or several appended (OPC 10000-6
    6.2.6: each is read by the length its DER header gives). ValueError when a part is not a DER
    certificate or the data ends inside one."""
    certs: list[x509.Certificate] = []
    offset = 0
    while offset < len(data):
        end = offset + der_length(data, offset)
        if end > len(data):
            raise ValueError(f"certificate {len(certs) + 1} of the chain is cut short")
        certs.append(x509.load_der_x509_certificate(data[offset:end]))
        offset = end
    if not certs:
        raise ValueError("no certificate")
    return certs


def first_certificate(data: bytes) -> bytes:
    """The user's own certificate of ``certificateData``: a client may send its issuers' after it, each
    a DER SEQUENCE (OPC 10000-6, 6.2.3: a chain is the certificates' encodings one after the other).
    ``data`` itself when it does not start with a well-formed SEQUENCE header."""
    try:
        end = der_length(data)
    except ValueError:
        return data
    return data[:end] if end <= len(data) else data


def der_length(data: bytes, offset: int = 0) -> int:
    """The full length (header included) of the DER SEQUENCE starting at ``offset``, as its header says
    (it may say more than ``data`` holds). ValueError when no SEQUENCE header starts there."""
    if offset + 2 > len(data) or data[offset] != 0x30:
        raise ValueError("not a DER certificate")
    first = data[offset + 1]
    if first < 0x80:
        return 2 + first
    count = first & 0x7F
    if not 1 <= count <= 4 or offset + 2 + count > len(data):
        raise ValueError("not a DER certificate")
    return 2 + count + int.from_bytes(data[offset + 2 : offset + 2 + count], "big")


def check_chain(
    chain: Sequence[x509.Certificate], anchors: Anchors, now: dt.datetime, *, require_crls: bool = True
) -> Refusal | None:
    """The first failing step for ``chain`` (the end certificate first, then what the client sent of
    its issuers), or None when it is trusted. See the module's text for the steps."""
    leaf = chain[0]
    weak = policy_problem(leaf)
    if weak is not None:
        return Refusal(_S.BadCertificatePolicyCheckFailed, leaf, weak)
    path, refusal = _build(leaf, [*chain[1:], *anchors.trusted, *anchors.issuers])
    if refusal is not None:
        if (
            refusal.code == _S.BadCertificateChainIncomplete
            and refusal.certificate == leaf
            and anchors.is_trusted(leaf)
        ):
            return None  # trusted by itself, its own issuer unknown: pinned (decision 92)
        return refusal
    if not any(anchors.is_trusted(c) for c in path):
        return Refusal(_S.BadCertificateUntrusted, leaf, "neither it nor an issuer of its chain is trusted")
    for issuer in path[1:]:
        if not issuer.not_valid_before_utc <= now <= issuer.not_valid_after_utc:
            return Refusal(_S.BadCertificateIssuerTimeInvalid, issuer, f"issuer {_name(issuer)} is not valid now")
    for issuer in path[1:]:
        if not may_sign_certificates(issuer):
            why = f"issuer {_name(issuer)} is not a CA that signs certificates"
            return Refusal(_S.BadCertificateIssuerUseNotAllowed, issuer, why)
    # a certificate trusted by itself needs no revocation list to be found (as before chains were checked:
    # an upgrade locks nobody out), but one that is there still counts
    return _revocation(path, anchors.crls, require_crls and not anchors.is_trusted(leaf), now)


def _build(
    leaf: x509.Certificate, candidates: Sequence[x509.Certificate]
) -> tuple[list[x509.Certificate], Refusal | None]:
    path = [leaf]
    while True:
        cert = path[-1]
        if is_self_signed(cert):
            return path, None  # a self-signed root ends the chain
        if len(path) >= MAX_DEPTH:
            return path, Refusal(_S.BadCertificateChainIncomplete, cert, f"the chain is longer than {MAX_DEPTH}")
        named = [c for c in candidates if c.subject == cert.issuer and c not in path]
        issuer = next((c for c in named if issued_by(cert, c)), None)
        if issuer is not None:
            weak = policy_problem(issuer)
            if weak is not None:
                return path, Refusal(_S.BadCertificatePolicyCheckFailed, issuer, weak)
        if issuer is None:
            if cert.issuer == cert.subject or named:
                return path, Refusal(_S.BadCertificateInvalid, cert, f"the signature of {_name(cert)} does not verify")
            return path, Refusal(
                _S.BadCertificateChainIncomplete, cert, f"its issuer {cert.issuer.rfc4514_string()} is not known"
            )
        path.append(issuer)


def policy_problem(cert: x509.Certificate) -> str | None:
    """What the Security Policy check (OPC 10000-4 6.1.3; OPC 10000-7 for the RSA policies uacell
    offers) finds wrong with ``cert``, in words, or None: its signature must be RSA over SHA-256, SHA-384
    or SHA-512 (a CA's, a root's own included, as well: Basic256Sha256 rejects a chain with any
    certificate signed otherwise), and an application's key (not a CA's) RSA of 2048 to 4096 bits."""
    try:
        digest = cert.signature_hash_algorithm
    except UnsupportedAlgorithm:
        digest = None
    if cert.signature_algorithm_oid not in POLICY_SIGNATURES or not isinstance(digest, POLICY_HASHES):
        used = getattr(cert.signature_algorithm_oid, "_name", cert.signature_algorithm_oid.dotted_string)
        return f"{_name(cert)} is signed with {used}; the security policies ask for RSA over SHA-256 or longer"
    return None if is_ca(cert) else key_problem(cert)


def key_problem(cert: x509.Certificate) -> str | None:
    """What the policies find wrong with the key of an application's (or a user's) certificate, or None:
    RSA of 2048 to 4096 bits (OPC 10000-7)."""
    key = cert.public_key()
    if not isinstance(key, rsa.RSAPublicKey):
        return f"{_name(cert)} has a {type(key).__name__} key; the security policies ask for RSA"
    if not MIN_KEY_BITS <= key.key_size <= MAX_KEY_BITS:
        return (
            f"{_name(cert)} has an RSA key of {key.key_size} bits; the security policies ask for "
            f"{MIN_KEY_BITS} to {MAX_KEY_BITS}"
        )
    return None


def is_ca(cert: x509.Certificate) -> bool:
    """Does ``cert`` say it is a CA's (RFC 5280 4.2.1.9)?"""
    try:
        return bool(cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        return False


def is_self_signed(cert: x509.Certificate) -> bool:
    return cert.issuer == cert.subject and issued_by(cert, cert)


def issued_by(cert: x509.Certificate, issuer: x509.Certificate) -> bool:
    try:
        cert.verify_directly_issued_by(issuer)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def may_sign_certificates(cert: x509.Certificate) -> bool:
    if not is_ca(cert):
        return False  # RFC 5280 4.2.1.9: a CA's certificate says it is one
    try:
        return cert.extensions.get_extension_for_class(x509.KeyUsage).value.key_cert_sign
    except x509.ExtensionNotFound:
        return True


def _revocation(
    path: Sequence[x509.Certificate],
    crls: Iterable[x509.CertificateRevocationList],
    require_crls: bool,
    now: dt.datetime,
) -> Refusal | None:
    crls = list(crls)
    for i, (cert, issuer) in enumerate(itertools.pairwise(path)):
        own = i == 0
        unknown = _S.BadCertificateRevocationUnknown if own else _S.BadCertificateIssuerRevocationUnknown
        crl = newest_crl(issuer, crls)
        if crl is None:
            if not require_crls:
                continue
            return Refusal(unknown, cert, f"no revocation list of {_name(issuer)} is known")
        if crl.get_revoked_certificate_by_serial_number(cert.serial_number) is not None:
            code = _S.BadCertificateRevoked if own else _S.BadCertificateIssuerRevoked
            return Refusal(code, cert, f"{_name(cert)} is revoked by {_name(issuer)}")
        due = crl.next_update_utc
        if require_crls and due is not None and due < now:
            # RFC 5280 6.3.3: a list past its nextUpdate no longer says whether a certificate was revoked since
            why = f"the revocation list of {_name(issuer)} was due to be renewed on {due:%Y-%m-%d %H:%M} UTC"
            return Refusal(unknown, cert, why)
    return None


def next_change(anchors: Anchors, now: dt.datetime) -> dt.datetime | None:
    """The first instant after ``now`` at which ``check_chain`` may answer otherwise for the same files,
    by time alone: a revocation list's nextUpdate passes (decision 98), or a trusted or issuer
    certificate begins or ends its validity. None when no such instant is ahead."""
    instants = [crl.next_update_utc for crl in anchors.crls]
    for cert in (*anchors.trusted, *anchors.issuers):
        instants += [cert.not_valid_before_utc, cert.not_valid_after_utc]
    return min((t for t in instants if t is not None and t > now), default=None)


def newest_crl(
    issuer: x509.Certificate, crls: Iterable[x509.CertificateRevocationList]
) -> x509.CertificateRevocationList | None:
    """The latest revocation list (by its thisUpdate) that ``issuer`` signed, if any."""
    key = issuer.public_key()
    own = [c for c in crls if c.issuer == issuer.subject and _crl_signed(c, key)]
    return max(own, key=lambda c: c.last_update_utc, default=None)


def _crl_signed(crl: x509.CertificateRevocationList, key: object) -> bool:
    try:
        return crl.is_signature_valid(key)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False


def _name(cert: x509.Certificate) -> str:
    return cert.subject.rfc4514_string() or "(no subject)"
