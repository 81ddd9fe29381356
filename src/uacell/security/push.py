"""The Server object's ServerConfiguration: the push model of certificate management (OPC 10000-12 7.10,
decision 96), for a GDS or a certificate manager that keeps the plant's servers' certificates.

- ``CreateSigningRequest(CertificateGroupId, CertificateTypeId, SubjectName, RegeneratePrivateKey, Nonce)
  -> CertificateRequest``: a PKCS #10 request, DER, for the server's key or (``RegeneratePrivateKey``,
  with a Nonce of at least 32 bytes) for a new key kept in ``pki/own/pending/`` until its certificate
  comes (the same as ``uacell cert request``, ``uacell.security.own_certificate``).
- ``UpdateCertificate(CertificateGroupId, CertificateTypeId, Certificate, IssuerCertificates,
  PrivateKeyFormat, PrivateKey) -> ApplyChangesRequired``: the certificate installed as ``uacell cert
  install`` does, with its checks and their codes; a private key made elsewhere in the "PEM" format.
  Always ApplyChangesRequired.
- ``ApplyChanges()``: secure channels opened from then on use the installed certificate; those open
  keep the one they were opened with until they close.
- ``GetRejectedList() -> Certificates``: the certificates in ``pki/rejected/``.
- The DefaultApplicationGroup's TrustList: ``AddCertificate(Certificate, IsTrustedCertificate)`` puts a
  certificate valid as OPC 10000-4 checks it (a CA's certificate's issuer already trusted or an issuer)
  into ``pki/trusted/``; ``RemoveCertificate(Thumbprint, IsTrustedCertificate)`` takes one out of
  ``pki/trusted/`` or ``pki/issuers/`` with the revocation lists it signed, unless it issued another
  certificate of the trust list (Bad_CertificateChainIncomplete). Issuers are added with their
  revocation lists by ``uacell cert``: AddCertificate with IsTrustedCertificate false is
  Bad_InvalidArgument, as 1.05 says issuers cannot be added this way.

The group is the DefaultApplicationGroup (or null), the type RsaSha256ApplicationCertificateType (or
null); anything else is Bad_InvalidArgument. Each method needs an admin over a SignAndEncrypt channel
(the standard's SecurityAdmin over an encrypted channel; Bad_SecurityModeInsufficient otherwise).

The TrustList is also served as a file (decision 97, ``uacell.security.trust_list_file``): Open (Read,
or Write + EraseExisting), OpenWithMasks, Read, Write, GetPosition, SetPosition, Close and
CloseAndUpdate, which replaces the lists the written TrustListDataType specifies at once
(ApplyChangesRequired false). AddCertificate and RemoveCertificate are Bad_InvalidState while the file
is open. OpenCount and LastUpdateTime follow; the handles close with their session, or when the
TrustList sees no call for its ActivityTimeout.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import ua
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID

from uacell.core.errors import CallError
from uacell.core.roles import Family
from uacell.host import ConfigurationHost
from uacell.security.chain import (
    Anchors,
    Refusal,
    check_chain,
    der_of,
    is_self_signed,
    issued_by,
    newest_crl,
    split_chain,
)
from uacell.security.own_certificate import (
    InstallRefused,
    install_certificate,
    own_issuers,
    read_certificates,
    signing_request,
)
from uacell.security.pki import PkiPaths, TrustList, load_server_key, revocation_lists, thumbprint
from uacell.security.trust_list_file import MODE_WRITE_ERASE, TrustListFile, last_update, update_lists
from uacell.ua import context
from uacell.ua.context import Caller
from uacell.ua.door.certificate import use_certificate
from uacell.ua.door.connection import channel_policy

log = logging.getLogger(__name__)

_O = ua.ObjectIds
CONFIGURATION = ua.NodeId(_O.ServerConfiguration)
GROUP = ua.NodeId(_O.ServerConfiguration_CertificateGroups_DefaultApplicationGroup)
TRUST_LIST = ua.NodeId(_O.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList)
CERTIFICATE_TYPE = ua.NodeId(_O.RsaSha256ApplicationCertificateType)
PRIVATE_KEY_FORMATS = ["PEM"]
MIN_NONCE = 32  # OPC 10000-12 7.10.10: the Nonce that comes with RegeneratePrivateKey

# OPC 10000-12 7.6.4: SubjectName's "Name=Value" pairs, separated by "/" or ","
_NAME_OIDS = {
    "CN": NameOID.COMMON_NAME,
    "O": NameOID.ORGANIZATION_NAME,
    "OU": NameOID.ORGANIZATIONAL_UNIT_NAME,
    "DC": NameOID.DOMAIN_COMPONENT,
    "L": NameOID.LOCALITY_NAME,
    "S": NameOID.STATE_OR_PROVINCE_NAME,
    "ST": NameOID.STATE_OR_PROVINCE_NAME,
    "C": NameOID.COUNTRY_NAME,
}


def subject_name(text: str) -> x509.Name:
    """The X.500 name ``text`` writes as OPC 10000-12 7.6.4 does ("CN=Line 3/O=Plant" or with commas);
    ValueError for anything else."""
    separator = "/" if "/" in text else ","
    attributes = []
    for part in (p.strip() for p in text.strip().strip("/").split(separator)):
        key, equals, value = part.partition("=")
        oid = _NAME_OIDS.get(key.strip().upper())
        if not equals or oid is None or not value.strip():
            raise ValueError(f"{part!r} is not one of {', '.join(_NAME_OIDS)} = a value")
        attributes.append(x509.NameAttribute(oid, value.strip().strip('"')))
    if not attributes:
        raise ValueError("no name")
    return x509.Name(attributes)


class ServerConfiguration:
    """The methods of ``Server.ServerConfiguration`` on one server (bound by ``bind``)."""

    def __init__(self, app: ConfigurationHost) -> None:
        self.app = app
        self.paths = PkiPaths.in_data_dir(app.data_dir)
        cfg = app.config.server
        self.application_uri, self.hosts = cfg.application_uri, [cfg.host]
        self.trust_file = TrustListFile(self.paths)
        self._expiry: asyncio.TimerHandle | None = None

    async def bind(self) -> None:
        dispatcher, family = self.app.dispatcher, Family.SERVER_CONFIGURATION
        for method, handler in (
            (_O.ServerConfiguration_CreateSigningRequest, self.create_signing_request),
            (_O.ServerConfiguration_UpdateCertificate, self.update_certificate),
            (_O.ServerConfiguration_ApplyChanges, self.apply_changes),
            (_O.ServerConfiguration_GetRejectedList, self.get_rejected_list),
        ):
            # one at a time: a request's pending key is not replaced while a certificate is installed
            dispatcher.bind(CONFIGURATION, ua.NodeId(method), family, handler, serialize_on=self)
        trust_list: tuple[tuple[str, Callable[..., Awaitable[list[Any]]]], ...] = (
            ("AddCertificate", self.add_certificate),
            ("RemoveCertificate", self.remove_certificate),
            ("Open", self.open),
            ("OpenWithMasks", self.open_with_masks),
            ("Read", self.read),
            ("Write", self.write),
            ("GetPosition", self.get_position),
            ("SetPosition", self.set_position),
            ("Close", self.close),
            ("CloseAndUpdate", self.close_and_update),
        )
        for name, method in trust_list:
            dispatcher.bind(TRUST_LIST, _trust_list_id(name), Family.TRUST_LIST, method, serialize_on=self)
        self._watch_sessions()
        aspace = self.app.server.iserver.aspace
        # two optional properties of TrustListType (1.05) the core NodeSet's instance does not carry
        timeout_ms = self.trust_file.activity_timeout * 1000
        for name, data_type, value in (
            ("ActivityTimeout", ua.NodeId(_O.Duration), ua.Variant(timeout_ms, ua.VariantType.Double)),
            ("MaxByteStringLength", ua.NodeId(_O.UInt32), ua.Variant(self.trust_file.max_read, ua.VariantType.UInt32)),
        ):
            node = self.app.server.get_node(_trust_list_id(name))
            try:
                await node.read_browse_name()
            except ua.UaStatusCodeError:
                await self.app.server.get_node(TRUST_LIST).add_property(
                    node.nodeid, ua.QualifiedName(name, 0), value, datatype=data_type
                )
        for node, value in (
            (
                ua.NodeId(_O.ServerConfiguration_SupportedPrivateKeyFormats),
                ua.Variant(PRIVATE_KEY_FORMATS, ua.VariantType.String),
            ),
            (ua.NodeId(_O.ServerConfiguration_ServerCapabilities), ua.Variant([], ua.VariantType.String)),
            (
                ua.NodeId(_O.ServerConfiguration_MaxTrustListSize),
                ua.Variant(self.trust_file.max_size, ua.VariantType.UInt32),
            ),
            (_trust_list_id("ActivityTimeout"), ua.Variant(timeout_ms, ua.VariantType.Double)),
            (_trust_list_id("MaxByteStringLength"), ua.Variant(self.trust_file.max_read, ua.VariantType.UInt32)),
            (_trust_list_id("Writable"), ua.Variant(True, ua.VariantType.Boolean)),
            (_trust_list_id("UserWritable"), ua.Variant(True, ua.VariantType.Boolean)),
            (ua.NodeId(_O.ServerConfiguration_MulticastDnsEnabled), ua.Variant(False, ua.VariantType.Boolean)),
            (
                ua.NodeId(_O.ServerConfiguration_CertificateGroups_DefaultApplicationGroup_CertificateTypes),
                ua.Variant([CERTIFICATE_TYPE], ua.VariantType.NodeId),
            ),
        ):
            await aspace.write_attribute_value(node, ua.AttributeIds.Value, ua.DataValue(value))
        await self._publish_trust_list()

    # -- the methods ---------------------------------------------------------------------------------

    async def create_signing_request(
        self, caller: Caller, group: ua.NodeId, certificate_type: ua.NodeId, subject: str, new_key: bool, nonce: bytes
    ) -> list[Any]:
        _encrypted(caller)
        _group_and_type(group, certificate_type)
        name = None
        if subject:
            try:
                name = subject_name(subject)
            except ValueError as exc:
                raise CallError("BadInvalidArgument", f"SubjectName: {exc}", argument=2) from None
        if new_key and len(nonce or b"") < MIN_NONCE:
            raise CallError("BadInvalidArgument", f"a new key needs a Nonce of {MIN_NONCE} bytes or more", argument=4)
        pem = await asyncio.to_thread(
            signing_request, self.paths, self.application_uri, self.hosts, new_key=new_key, subject=name
        )
        request = x509.load_pem_x509_csr(pem).public_bytes(serialization.Encoding.DER)
        who = caller.display_user
        log.info("a certificate signing request for %s (new key: %s) by %s", name or "the subject", new_key, who)
        return [request]

    async def update_certificate(
        self,
        caller: Caller,
        group: ua.NodeId,
        certificate_type: ua.NodeId,
        certificate: bytes,
        issuers: list[bytes] | None,
        key_format: str,
        private_key: bytes,
    ) -> list[Any]:
        _encrypted(caller)
        _group_and_type(group, certificate_type)
        key = _private_key(key_format, private_key) if private_key else None
        data = (certificate or b"") + b"".join(i or b"" for i in issuers or [])
        try:
            done = await asyncio.to_thread(
                install_certificate, self.paths, data, self.application_uri, self.hosts, private_key=key
            )
        except InstallRefused as refused:
            raise CallError(refused.code, f"the certificate is refused: {refused}") from None
        log.warning(
            "server certificate %s from %s installed by %s (used by new secure channels after ApplyChanges)",
            thumbprint(der_of(done.certificate)),
            done.certificate.issuer.rfc4514_string(),
            caller.display_user,
        )
        return [True]

    async def apply_changes(self, caller: Caller) -> list[Any]:
        _encrypted(caller)
        certificate = x509.load_der_x509_certificate(self.paths.cert.read_bytes())
        key = await asyncio.to_thread(load_server_key, self.paths)
        issuers = b"".join(der_of(c) for c in own_issuers(self.paths, certificate))
        use_certificate(self.app.server, certificate, key, issuers)
        log.warning("ApplyChanges by %s: new secure channels use %s", caller.display_user, self.paths.cert)
        return []

    # -- the DefaultApplicationGroup's TrustList, a certificate at a time (OPC 10000-12 7.8.2.6, 7.8.2.7) --

    async def add_certificate(self, caller: Caller, certificate: bytes, trusted: bool) -> list[Any]:
        self._trust_list_call(caller)
        self.trust_file.refuse_changes()
        if not trusted:
            why = "a CA's certificate comes with its revocation lists: `uacell cert issuer` and `uacell cert crl`"
            raise CallError("BadInvalidArgument", why, argument=1)
        try:
            cert = split_chain(certificate or b"")[0]
        except ValueError:
            raise CallError("BadCertificateInvalid", "not a DER certificate", argument=0) from None
        trust_list = TrustList(self.paths)
        refusal = addable(cert, trust_list.anchors(), datetime.now(UTC))
        if refusal is not None:
            raise CallError(ua.StatusCode(refusal.code).name, f"not added: {refusal.why}", argument=0)
        path = await asyncio.to_thread(trust_list.trust, der_of(cert))
        log.warning("%s trusted %s by AddCertificate (%s)", caller.display_user, path.stem, path)
        await self._publish_trust_list()
        return []

    async def remove_certificate(self, caller: Caller, thumbprint_hex: str, trusted: bool) -> list[Any]:
        self._trust_list_call(caller)
        self.trust_file.refuse_changes()
        folder = self.paths.trusted if trusted else self.paths.issuers
        wanted = (thumbprint_hex or "").strip().lower()
        anchors = TrustList(self.paths).anchors()
        files = [(f, c) for f, c in _certificate_files(folder) if thumbprint(der_of(c)) == wanted]
        if not files:
            where = "trusted" if trusted else "issuer"
            raise CallError("BadInvalidArgument", f"no {where} certificate has the thumbprint {wanted!r}", argument=0)
        cert = files[0][1]
        others = [c for c in (*anchors.trusted, *anchors.issuers) if c != cert and not is_self_signed(c)]
        if any(issued_by(c, cert) for c in others):
            raise CallError("BadCertificateChainIncomplete", f"{wanted} issued a certificate of the trust list")
        for f, _ in files:
            f.unlink(missing_ok=True)
        for f, crl in revocation_lists(self.paths):
            if newest_crl(cert, [crl]) is not None:  # one it signed
                f.unlink(missing_ok=True)
        log.warning("%s removed %s from the %s certificates", caller.display_user, wanted, folder.name)
        self.app.security.recheck_channels()
        await self._publish_trust_list()
        return []

    # -- the TrustList as a file (OPC 10000-12 7.8.2.1 to 7.8.2.5; uacell.security.trust_list_file) ----------

    async def open(self, caller: Caller, mode: int) -> list[Any]:
        self._trust_list_call(caller)
        handle = self.trust_file.open(caller.session_id, mode)
        if mode == MODE_WRITE_ERASE:
            log.info("%s opened the trust list for writing", caller.display_user)
        await self._publish_trust_list()
        return [handle]

    async def open_with_masks(self, caller: Caller, masks: int) -> list[Any]:
        self._trust_list_call(caller)
        handle = self.trust_file.open_with_masks(caller.session_id, masks)
        await self._publish_trust_list()
        return [handle]

    async def read(self, caller: Caller, handle: int, length: int) -> list[Any]:
        self._trust_list_call(caller)
        return [self.trust_file.read(caller.session_id, handle, length)]

    async def write(self, caller: Caller, handle: int, data: bytes | None) -> list[Any]:
        self._trust_list_call(caller)
        self.trust_file.write(caller.session_id, handle, data or b"")
        return []

    async def get_position(self, caller: Caller, handle: int) -> list[Any]:
        self._trust_list_call(caller)
        return [self.trust_file.get_position(caller.session_id, handle)]

    async def set_position(self, caller: Caller, handle: int, position: int) -> list[Any]:
        self._trust_list_call(caller)
        self.trust_file.set_position(caller.session_id, handle, position)
        return []

    async def close(self, caller: Caller, handle: int) -> list[Any]:
        self._trust_list_call(caller)
        self.trust_file.close(caller.session_id, handle)
        await self._publish_trust_list()
        return []

    async def close_and_update(self, caller: Caller, handle: int) -> list[Any]:
        self._trust_list_call(caller)
        written = self.trust_file.close_written(caller.session_id, handle)  # on the loop, as every handle change
        try:
            checked = await asyncio.to_thread(update_lists, self.paths, written, datetime.now(UTC))
        finally:
            await self._publish_trust_list()  # closed, whatever the update's outcome
        closed = self.app.security.recheck_channels()
        log.warning(
            "%s replaced the trust list by CloseAndUpdate: %d trusted, %d issuer certificates, %d revocation lists; "
            "%d secure channel(s) it no longer admits closed",
            caller.display_user,
            len(checked.trusted),
            len(checked.issuers),
            len(checked.crls),
            len(closed),
        )
        return [False]  # applied at once: no transaction, no ApplyChanges needed

    def _trust_list_call(self, caller: Caller) -> None:
        """Every call on the TrustList: an encrypted channel, and its activity timeout started again."""
        _encrypted(caller)
        if self.trust_file.touch():
            self.app.publisher.submit(self._publish_trust_list)
        if self._expiry is not None:
            self._expiry.cancel()
        loop = asyncio.get_running_loop()
        self._expiry = loop.call_later(self.trust_file.activity_timeout + 0.1, self._expire)

    def _expire(self) -> None:
        self._expiry = None
        if self.trust_file.expire():
            self.app.publisher.submit(self._publish_trust_list)

    def _watch_sessions(self) -> None:
        def closed(session: Any) -> None:
            if self.trust_file.close_session(context.caller_of(session).session_id):
                self.app.publisher.submit(self._publish_trust_list)

        self.app.security.on_session_closed.append(closed)
        # LastUpdateTime follows the files whoever changes them (``uacell cert``: decision 100)
        self.app.security.on_trust_changed.append(lambda: self.app.publisher.submit(self._publish_trust_list))

    async def _publish_trust_list(self) -> None:
        """The TrustList's OpenCount and LastUpdateTime as they are now."""
        aspace = self.app.server.iserver.aspace
        last = await asyncio.to_thread(last_update, self.paths)
        for node, value in (
            (_trust_list_id("OpenCount"), ua.Variant(self.trust_file.open_count, ua.VariantType.UInt16)),
            (_trust_list_id("LastUpdateTime"), ua.Variant(last, ua.VariantType.DateTime)),
        ):
            await aspace.write_attribute_value(node, ua.AttributeIds.Value, ua.DataValue(value))

    async def get_rejected_list(self, caller: Caller) -> list[Any]:
        _encrypted(caller)
        folder = self.paths.rejected
        found = sorted(folder.iterdir()) if folder.is_dir() else []
        return [[f.read_bytes() for f in found if f.is_file() and f.suffix.lower() == ".der"]]


def addable(cert: x509.Certificate, anchors: Anchors, now: datetime) -> Refusal | None:
    """Why ``cert`` may not be added to the trusted certificates (OPC 10000-12 7.8.2.6: valid as OPC
    10000-4 checks it, and a CA's certificate's issuer already in the trust list), or None."""
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        return Refusal(ua.StatusCodes.BadCertificateTimeInvalid, cert, "it is not valid now")
    refusal = check_chain([cert], Anchors((cert, *anchors.trusted), anchors.issuers, anchors.crls), now)
    if refusal is not None:
        return refusal
    if not is_self_signed(cert) and not any(issued_by(cert, c) for c in (*anchors.trusted, *anchors.issuers)):
        why = f"its issuer {cert.issuer.rfc4514_string()} is not in the trust list"
        return Refusal(ua.StatusCodes.BadCertificateChainIncomplete, cert, why)
    return None


def _trust_list_id(name: str) -> ua.NodeId:
    """A member of the DefaultApplicationGroup's TrustList, by its BrowseName."""
    return ua.NodeId(getattr(_O, f"ServerConfiguration_CertificateGroups_DefaultApplicationGroup_TrustList_{name}"))


def _certificate_files(folder: Path) -> list[tuple[Path, x509.Certificate]]:
    found = []
    for f in sorted(folder.iterdir()) if folder.is_dir() else []:
        try:
            found.append((f, read_certificates(f.read_bytes())[0]))
        except (OSError, ValueError):
            continue
    return found


def _encrypted(caller: Caller) -> None:
    """OPC 10000-12 7.10: these methods are called over an encrypted channel."""
    _, mode = channel_policy(context.current_processor())
    if mode != ua.MessageSecurityMode.SignAndEncrypt:
        raise CallError("BadSecurityModeInsufficient", f"{caller.display_user} called over a {mode.name} channel")


def _group_and_type(group: ua.NodeId, certificate_type: ua.NodeId) -> None:
    if not group.is_null() and group != GROUP:
        raise CallError("BadInvalidArgument", f"no certificate group {group.to_string()}", argument=0)
    if not certificate_type.is_null() and certificate_type != CERTIFICATE_TYPE:
        raise CallError("BadInvalidArgument", f"no certificate type {certificate_type.to_string()} here", argument=1)


def _private_key(key_format: str, data: bytes) -> rsa.RSAPrivateKey:
    if key_format != "PEM":
        raise CallError("BadNotSupported", f"private key format {key_format!r}: only PEM", argument=4)
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError):
        raise CallError("BadInvalidArgument", "the private key is no unencrypted PEM key", argument=5) from None
    if not isinstance(key, rsa.RSAPrivateKey) or key.key_size < 2048:
        raise CallError("BadInvalidArgument", "the private key is no RSA key of 2048 bits or more", argument=5)
    return key
