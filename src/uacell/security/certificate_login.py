"""Logins with an X.509 user certificate: the X509IdentityToken of ActivateSession (decision 84).

OPC 10000-4 (5.6.3, 7.41.5): the client sends the user's certificate (DER) and a ``userTokenSignature``
made with the user's private key over the server's certificate followed by the last server nonce the
session was sent, with the asymmetric signature algorithm of the user token policy's security policy
(OPC 10000-7). uacell checks, in this order, and answers the first that fails:

1. the certificate can be read (``Bad_IdentityTokenInvalid``);
2. the signature uses the policy's algorithm and verifies with the certificate's key: the client holds
   the private key, for this session and this nonce (``Bad_UserSignatureInvalid``);
3. its key is one the policies allow, RSA of 2048 to 4096 bits (decision 102), it is valid now and,
   if it says what its key is for, signing is among it (``Bad_IdentityTokenRejected``);
4. it is bound to a user in ``users.toml`` (``Bad_IdentityTokenRejected``): the administrator's
   binding is what makes a user certificate trusted, as the trust list does for applications.

A refusal at steps 3 and 4 also names the certificate step that failed (``certificate_code``:
Bad_CertificatePolicyCheckFailed, Bad_CertificateTimeInvalid, Bad_CertificateUseNotAllowed,
Bad_CertificateUntrusted), for the AuditCertificate event the server fires besides the session's
(decision 102).

The proof of possession comes before anything about the user store is said, so a client without the
key learns nothing from the answer. Pure apart from the user store's file: no OPC UA stack here.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import padding, rsa

from uacell.core.roles import Role
from uacell.security.chain import first_certificate, key_problem
from uacell.security.users import UserStore, thumbprint

RSA_SHA256 = "http://www.w3.org/2001/04/xmldsig-more#rsa-sha256"
RSA_PSS_SHA256 = "http://opcfoundation.org/UA/security/rsa-pss-sha2-256"
_POLICY = "http://opcfoundation.org/UA/SecurityPolicy#"
# OPC 10000-7: the AsymmetricSignatureAlgorithm of each security policy uacell offers.
SIGNATURE_ALGORITHM: dict[str, str] = {
    f"{_POLICY}Basic256Sha256": RSA_SHA256,
    f"{_POLICY}Aes128_Sha256_RsaOaep": RSA_SHA256,
    f"{_POLICY}Aes256_Sha256_RsaPss": RSA_PSS_SHA256,
}
_PADDING = {
    RSA_SHA256: padding.PKCS1v15(),
    RSA_PSS_SHA256: padding.PSS(mgf=padding.MGF1(hashes.SHA256()), salt_length=32),
}

# status codes (OPC 10000-4, ActivateSession's results), as numbers: no OPC UA stack here
BAD_IDENTITY_TOKEN_INVALID = 0x80200000
BAD_IDENTITY_TOKEN_REJECTED = 0x80210000
BAD_USER_SIGNATURE_INVALID = 0x80570000
BAD_CERTIFICATE_TIME_INVALID = 0x80140000
BAD_CERTIFICATE_USE_NOT_ALLOWED = 0x80180000
BAD_CERTIFICATE_UNTRUSTED = 0x801A0000
BAD_CERTIFICATE_POLICY_CHECK_FAILED = 0x81140000


class TokenRefused(Exception):
    """The login is refused with ``code``; ``why`` is for the server's log, never for the client;
    ``certificate_code``: the certificate step that failed, when the certificate is what was refused."""

    def __init__(self, code: int, why: str, certificate_code: int | None = None) -> None:
        super().__init__(why)
        self.code = code
        self.why = why
        self.certificate_code = certificate_code


@dataclass(frozen=True)
class CertificateLogin:
    """Who a certificate logged in as."""

    user: str
    role: Role
    thumbprint: str
    expires: datetime  # the certificate's notAfter (UTC): the session's credentials end then (decision 88)


class VerifiedCertificate(bytes):
    """The DER of a user certificate that passed ``check_user_certificate``, carrying who it logged in as.

    asyncua hands what its X.509 hook returns to the user manager as ``certificate``, the same argument
    that carries the secure channel's application certificate for every other login; only this type
    says a user certificate was checked."""

    login: CertificateLogin

    @classmethod
    def of(cls, der: bytes, login: CertificateLogin) -> VerifiedCertificate:
        verified = cls(der)
        verified.login = login
        return verified


def check_user_certificate(
    der: bytes | None,
    algorithm: str | None,
    signature: bytes | None,
    *,
    policy_uri: str,
    challenge: bytes,
    now: datetime,
    chain_challenge: bytes | None = None,
    users: UserStore,
) -> CertificateLogin:
    """The user an X509IdentityToken logs in as, or TokenRefused (the module's steps, in order).

    ``challenge``: the server certificate's DER followed by the last server nonce sent to the session;
    ``chain_challenge``: the same with the server's whole chain, when it sends one (OPC 10000-4 5.7.3.2:
    a signature over the chain is accepted when the one over the certificate alone does not verify);
    ``policy_uri``: the security policy of the user token policy the token names; ``now``: aware UTC."""
    der = first_certificate(der or b"")
    try:
        cert = x509.load_der_x509_certificate(der)
    except ValueError:
        raise TokenRefused(BAD_IDENTITY_TOKEN_INVALID, "the certificate cannot be read") from None
    thumb = thumbprint(der)
    expected = SIGNATURE_ALGORITHM.get(policy_uri)
    if expected is None:
        raise TokenRefused(BAD_USER_SIGNATURE_INVALID, f"no signature algorithm for the policy {policy_uri!r}")
    if not signature:
        raise TokenRefused(BAD_USER_SIGNATURE_INVALID, f"certificate {thumb}: the token is not signed")
    if algorithm != expected:
        raise TokenRefused(
            BAD_USER_SIGNATURE_INVALID,
            f"certificate {thumb}: signed with {algorithm or 'nothing'}, the policy asks {expected}",
        )
    key = cert.public_key()
    if not isinstance(key, rsa.RSAPublicKey):
        raise TokenRefused(BAD_USER_SIGNATURE_INVALID, f"certificate {thumb}: its key is not an RSA key")
    if not any(_verifies(key, signature, data, expected) for data in (challenge, chain_challenge) if data is not None):
        raise TokenRefused(
            BAD_USER_SIGNATURE_INVALID,
            f"certificate {thumb}: the signature does not verify (another key, or not this session's nonce)",
        )
    weak = key_problem(cert)
    if weak is not None:
        why = f"certificate {thumb}: {weak}"
        raise TokenRefused(BAD_IDENTITY_TOKEN_REJECTED, why, BAD_CERTIFICATE_POLICY_CHECK_FAILED)
    if now < cert.not_valid_before_utc or now > cert.not_valid_after_utc:
        span = f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M} to {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"
        why = f"certificate {thumb} is not valid now (valid {span})"
        raise TokenRefused(BAD_IDENTITY_TOKEN_REJECTED, why, BAD_CERTIFICATE_TIME_INVALID)
    try:
        usage = cert.extensions.get_extension_for_class(x509.KeyUsage).value
    except x509.ExtensionNotFound:
        usage = None
    if usage is not None and not usage.digital_signature:
        why = f"certificate {thumb}: its key usage does not allow signing"
        raise TokenRefused(BAD_IDENTITY_TOKEN_REJECTED, why, BAD_CERTIFICATE_USE_NOT_ALLOWED)
    found = users.user_of_certificate(der)
    if found is None:
        why = f"certificate {thumb} is bound to no user"
        raise TokenRefused(BAD_IDENTITY_TOKEN_REJECTED, why, BAD_CERTIFICATE_UNTRUSTED)
    return CertificateLogin(found[0], found[1], thumb, cert.not_valid_after_utc)


def _verifies(key: rsa.RSAPublicKey, signature: bytes, data: bytes, algorithm: str) -> bool:
    try:
        key.verify(signature, data, _PADDING[algorithm], hashes.SHA256())
    except InvalidSignature:
        return False
    return True
