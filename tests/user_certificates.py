"""User certificates as a plant's PKI would issue them, made here with the cryptography package from
X.509's own rules (RFC 5280), not with uacell's code; and the userTokenSignature a client makes with
one, as OPC 10000-4 5.6.3 and OPC 10000-7 describe it."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import padding, rsa
from cryptography.x509.oid import NameOID

RSA_SHA256 = "http://www.w3.org/2001/04/xmldsig-more#rsa-sha256"
RSA_PSS_SHA256 = "http://opcfoundation.org/UA/security/rsa-pss-sha2-256"
BASIC256SHA256 = "http://opcfoundation.org/UA/SecurityPolicy#Basic256Sha256"
AES256_RSAPSS = "http://opcfoundation.org/UA/SecurityPolicy#Aes256_Sha256_RsaPss"


@dataclass
class UserCertificate:
    der: bytes
    key: rsa.RSAPrivateKey

    @property
    def key_pem(self) -> bytes:
        return self.key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    @property
    def pem(self) -> bytes:
        return x509.load_der_x509_certificate(self.der).public_bytes(serialization.Encoding.PEM)

    def sign(self, data: bytes, algorithm: str = RSA_SHA256) -> bytes:
        """The userTokenSignature of ``data`` (server certificate + server nonce) by ``algorithm``."""
        if algorithm == RSA_PSS_SHA256:
            pss = padding.PSS(mgf=padding.MGF1(hashes.SHA256()), salt_length=32)
            return self.key.sign(data, pss, hashes.SHA256())
        return self.key.sign(data, padding.PKCS1v15(), hashes.SHA256())

    def write(self, directory: Path, name: str) -> tuple[Path, Path]:
        """The certificate (PEM) and its key (PEM) as files."""
        directory.mkdir(parents=True, exist_ok=True)
        cert, key = directory / f"{name}-cert.pem", directory / f"{name}-key.pem"
        cert.write_bytes(self.pem)
        key.write_bytes(self.key_pem)
        return cert, key


def user_certificate(
    common_name: str,
    *,
    not_before: dt.datetime | None = None,
    days: int = 365,
    key_usage: bool = True,
    digital_signature: bool = True,
    key: rsa.RSAPrivateKey | None = None,
) -> UserCertificate:
    """A self-signed user certificate for ``common_name`` (RSA 2048, SHA-256)."""
    key = key or rsa.generate_private_key(public_exponent=65537, key_size=2048)
    start = not_before or dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    builder = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
    )
    if key_usage:
        builder = builder.add_extension(
            x509.KeyUsage(
                digital_signature=digital_signature,
                content_commitment=False,
                key_encipherment=not digital_signature,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
    cert = builder.sign(key, hashes.SHA256())
    return UserCertificate(cert.public_bytes(serialization.Encoding.DER), key)
