"""A plant's certificate authority, as a GDS or an IT department runs one, made here with the
cryptography package from X.509's own rules (RFC 5280: a CA's BasicConstraints and keyCertSign, CRLs
with revoked serial numbers) and OPC 10000-6 6.2.2 (an Application Instance Certificate: the
ApplicationUri in subjectAltName, the key usages, clientAuth), not with uacell's code. A chain is the
DER encodings appended, the application's first (OPC 10000-6 6.2.6)."""

from __future__ import annotations

import datetime as dt
import socket
import struct
from dataclasses import dataclass, field

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import padding, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

_KEYS: list[rsa.RSAPrivateKey] = []  # RSA keys take a while to make: a test module reuses a few


def _key(i: int) -> rsa.RSAPrivateKey:
    while len(_KEYS) <= i:
        _KEYS.append(rsa.generate_private_key(public_exponent=65537, key_size=2048))
    return _KEYS[i]


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.COMMON_NAME, common_name), x509.NameAttribute(NameOID.ORGANIZATION_NAME, "Plant")]
    )


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


@dataclass
class Authority:
    """A CA: its certificate and key, what it revoked, and the certificates it issued."""

    cert: x509.Certificate
    key: rsa.RSAPrivateKey
    revoked: list[int] = field(default_factory=list)

    @property
    def der(self) -> bytes:
        return self.cert.public_bytes(serialization.Encoding.DER)

    @classmethod
    def root(cls, common_name: str = "Plant Root CA", *, key_index: int = 0) -> Authority:
        key = _key(key_index)
        cert = _ca_builder(_name(common_name), _name(common_name), key.public_key()).sign(key, hashes.SHA256())
        return cls(cert, key)

    def intermediate(
        self,
        common_name: str = "Plant Issuing CA",
        *,
        key_index: int = 1,
        ca: bool = True,
        not_before: dt.datetime | None = None,
        days: int = 3650,
    ) -> Authority:
        key = _key(key_index)
        builder = _ca_builder(
            _name(common_name), self.cert.subject, key.public_key(), ca=ca, start=not_before, days=days
        )
        return Authority(builder.sign(self.key, hashes.SHA256()), key)

    def application(
        self,
        application_uri: str,
        common_name: str = "Line 3 MES",
        *,
        key_index: int = 2,
        key: rsa.RSAPrivateKey | None = None,
        not_after: dt.datetime | None = None,
    ) -> tuple[x509.Certificate, rsa.RSAPrivateKey]:
        """An Application Instance Certificate for a client, issued by this CA (with ``key`` instead of a
        shared 2048-bit one; valid until ``not_after`` instead of a year)."""
        key = key or _key(key_index)
        issuer = (self.cert.subject, self.key)
        return application_certificate(application_uri, common_name, key, issuer, not_after=not_after), key

    def sign_request(
        self,
        request_pem: bytes,
        *,
        days: int = 365,
        not_before: dt.datetime | None = None,
        usages: tuple[str, ...] = ("digital_signature", "content_commitment", "key_encipherment", "data_encipherment"),
        extended: tuple[x509.ObjectIdentifier, ...] = (
            ExtendedKeyUsageOID.SERVER_AUTH,
            ExtendedKeyUsageOID.CLIENT_AUTH,
        ),
        names: list[x509.GeneralName] | None = None,
    ) -> x509.Certificate:
        """What the CA issues for a PKCS #10 request (RFC 2986) it approved: the request's subject and key, the
        subjectAltName it asked for (or ``names``), the CA's own choice of validity and key usages (OPC
        10000-6 6.2.2: a server's Application Instance Certificate)."""
        request = x509.load_pem_x509_csr(request_pem)
        assert request.is_signature_valid, "a CA refuses a request its key did not sign"
        if names is None:
            names = list(request.extensions.get_extension_for_class(x509.SubjectAlternativeName).value)
        start = not_before or _now() - dt.timedelta(minutes=5)
        return (
            x509.CertificateBuilder()
            .subject_name(request.subject)
            .issuer_name(self.cert.subject)
            .public_key(request.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start)
            .not_valid_after(start + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(key_usage(*usages), critical=True)
            .add_extension(x509.ExtendedKeyUsage(list(extended)), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(self.key.public_key()), critical=False)
            .sign(self.key, hashes.SHA256())
        )

    def revoke(self, cert: x509.Certificate) -> None:
        self.revoked.append(cert.serial_number)

    def crl(
        self,
        *,
        signer: rsa.RSAPrivateKey | None = None,
        issued: dt.datetime | None = None,
        next_update: dt.datetime | None = None,
    ) -> bytes:
        """This CA's revocation list, DER, issued a minute ago (or at ``issued``), due for renewal a week
        later (or at ``next_update``: RFC 5280 5.1.2.5); signed by ``signer`` to forge one."""
        issued = issued or _now() - dt.timedelta(minutes=1)
        builder = (
            x509.CertificateRevocationListBuilder()
            .issuer_name(self.cert.subject)
            .last_update(issued)
            .next_update(next_update or issued + dt.timedelta(days=7))
        )
        for serial in self.revoked:
            builder = builder.add_revoked_certificate(
                x509.RevokedCertificateBuilder().serial_number(serial).revocation_date(_now()).build()
            )
        return builder.sign(signer or self.key, hashes.SHA256()).public_bytes(serialization.Encoding.DER)


def application_certificate(
    application_uri: str,
    common_name: str,
    key: rsa.RSAPrivateKey,
    issuer: tuple[x509.Name, rsa.RSAPrivateKey] | None = None,
    *,
    not_after: dt.datetime | None = None,
) -> x509.Certificate:
    """An Application Instance Certificate (OPC 10000-6 6.2.2) for ``key``, signed with SHA-256: issued by
    ``issuer`` (its name and key), or self-signed as most OPC UA applications make their own; valid from
    five minutes ago until ``not_after`` (a year by default)."""
    subject = _name(common_name)
    issuer_name, issuer_key = issuer or (subject, key)
    start = _now() - dt.timedelta(minutes=5)
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(not_after or start + dt.timedelta(days=365))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.UniformResourceIdentifier(application_uri), x509.DNSName(socket.gethostname())]
            ),
            critical=False,
        )
        .add_extension(
            # OPC 10000-6 6.2.2: an Application Instance Certificate's key usages
            key_usage("digital_signature", "content_commitment", "key_encipherment", "data_encipherment"),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_key.public_key()), critical=False)
        .sign(issuer_key, hashes.SHA256())
    )


_SHA256_WITH_RSA = bytes.fromhex("06092a864886f70d01010b")  # the OID 1.2.840.113549.1.1.11, DER
_SHA1_WITH_RSA = bytes.fromhex("06092a864886f70d010105")  # 1.2.840.113549.1.1.5 (RFC 3279 2.2.1)


def signed_with_sha1(cert: x509.Certificate, issuer_key: rsa.RSAPrivateKey) -> x509.Certificate:
    """``cert`` (signed with SHA-256 by ``issuer_key``) signed again with SHA-1, as old PKIs issued them:
    RFC 5280 4.1.1.2 and 4.1.2.3 name the algorithm twice, in the TBSCertificate and around it, and the
    two OIDs have the same length, so the DER changes in place (the cryptography package no longer signs
    certificates with SHA-1, but still computes a PKCS #1 v1.5 signature over SHA-1)."""
    whole, tbs = cert.public_bytes(serialization.Encoding.DER), cert.tbs_certificate_bytes
    assert whole.count(_SHA256_WITH_RSA) == 2 and tbs.count(_SHA256_WITH_RSA) == 1
    new_tbs = tbs.replace(_SHA256_WITH_RSA, _SHA1_WITH_RSA)
    signature = issuer_key.sign(new_tbs, padding.PKCS1v15(), hashes.SHA1())
    assert len(signature) == len(cert.signature)
    new = whole.replace(tbs, new_tbs).replace(_SHA256_WITH_RSA, _SHA1_WITH_RSA).replace(cert.signature, signature)
    return x509.load_der_x509_certificate(new)


def _ca_builder(
    subject: x509.Name,
    issuer: x509.Name,
    public: rsa.RSAPublicKey,
    *,
    ca: bool = True,
    start: dt.datetime | None = None,
    days: int = 3650,
) -> x509.CertificateBuilder:
    start = start or _now() - dt.timedelta(minutes=5)
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
        .add_extension(
            key_usage("key_cert_sign", "crl_sign") if ca else key_usage(),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
    )


def key_usage(*allowed: str) -> x509.KeyUsage:
    """A KeyUsage extension (RFC 5280 4.2.1.3) allowing the usages named, and nothing else."""
    names = (
        "digital_signature",
        "content_commitment",
        "key_encipherment",
        "data_encipherment",
        "key_agreement",
        "key_cert_sign",
        "crl_sign",
        "encipher_only",
        "decipher_only",
    )
    return x509.KeyUsage(**{name: name in allowed for name in names})


def der(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.DER)


def pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def key_pem(key: rsa.RSAPrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def byte_string_array(items: list[bytes] | None) -> bytes:
    """OPC 10000-6 5.2.5 and 5.2.2.7: an Int32 length (-1 for null), then each ByteString as an Int32 length
    and its bytes."""
    if items is None:
        return struct.pack("<i", -1)
    return struct.pack("<i", len(items)) + b"".join(struct.pack("<i", len(i)) + i for i in items)


def trust_list_bytes(
    masks: int,
    trusted: list[bytes] | None = None,
    trusted_crls: list[bytes] | None = None,
    issuers: list[bytes] | None = None,
    issuer_crls: list[bytes] | None = None,
) -> bytes:
    """TrustListDataType (OPC 10000-12 7.8.2.8): SpecifiedLists (UInt32) and the four ByteString arrays."""
    return struct.pack("<I", masks) + b"".join(
        byte_string_array(x) for x in (trusted, trusted_crls, issuers, issuer_crls)
    )


def parse_trust_list(data: bytes) -> tuple[int, list[list[bytes] | None]]:
    """SpecifiedLists and the four arrays of a TrustListDataType, read by OPC 10000-6 5.2's rules; the data
    must hold exactly one."""
    (masks,) = struct.unpack_from("<I", data)
    at = 4
    arrays: list[list[bytes] | None] = []
    for _ in range(4):
        (count,) = struct.unpack_from("<i", data, at)
        at += 4
        if count < 0:
            arrays.append(None)
            continue
        items = []
        for _ in range(count):
            (length,) = struct.unpack_from("<i", data, at)
            items.append(data[at + 4 : at + 4 + length])
            at += 4 + length
        arrays.append(items)
    assert at == len(data), f"{len(data) - at} bytes after the TrustListDataType"
    return int(masks), arrays
