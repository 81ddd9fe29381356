"""The trust list as a file (OPC 10000-12 7.8.2 TrustListType, decision 97): what a GDS reads and writes
through the DefaultApplicationGroup's TrustList object. Pure: the files under ``pki/`` and per-session
handles; ``uacell.security.push`` binds it.

The file is one TrustListDataType in the OPC UA binary encoding (OPC 10000-12 7.8.2.8): SpecifiedLists
(TrustListMasks: 1 TrustedCertificates, 2 TrustedCrls, 4 IssuerCertificates, 8 IssuerCrls) and the four
arrays of ByteStrings (DER certificates and revocation lists). uacell keeps them as ``pki/trusted/``,
``pki/issuers/`` and ``pki/crl/``; a revocation list in ``pki/crl/`` is a trusted CRL when a certificate
of ``pki/trusted/`` signed it, an issuer CRL otherwise.

- ``Open(0x01)`` or ``OpenWithMasks(masks)`` takes a snapshot of the lists as they are: what the
  handle reads stays consistent whatever changes meanwhile. Other modes than Read and Write +
  EraseExisting (0x06) are Bad_NotSupported.
- ``Open(0x06)``: one writer at a time, and no writer while a reader is open (Bad_NotWritable), no
  reader while a writer is (Bad_NotReadable). What is written stays in memory (at most ``max_size``
  bytes, Bad_ResourceUnavailable beyond) until ``CloseAndUpdate`` decodes it, checks it and replaces
  the lists its SpecifiedLists names, or ``Close`` drops it.
- ``CloseAndUpdate`` closes the handle whatever happens; a structure that does not decode is
  Bad_DecodingError, a certificate or revocation list that does not pass ``check_content`` its
  certificate code, and the files are then unchanged. Changes apply at once (no transactions): the
  answer's ApplyChangesRequired is false.
- A handle belongs to its session; a session's handles close with it, and every handle closes when
  the TrustList object sees no call for ``activity_timeout`` seconds (its ActivityTimeout).

The lists are replaced so that a crash cannot leave a mixture: the new content of each replaced folder
is written to ``pki/trust-update/`` with a marker last, then copied into place and the files it does
not hold removed; ``finish_update`` at start completes a replacement that a crash cut short.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from asyncua import ua
from asyncua.common.utils import Buffer, NotEnoughData
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from uacell.core.errors import CallError
from uacell.core.file_paths import MODE_ERASE_EXISTING, MODE_READ, MODE_WRITE, fsync_dir
from uacell.core.files import atomic_write
from uacell.security.chain import (
    der_of,
    is_self_signed,
    issued_by,
    may_sign_certificates,
    newest_crl,
    policy_problem,
)
from uacell.security.pki import (
    CERT_SUFFIXES,
    CRL_SUFFIXES,
    PkiPaths,
    certificate_file_name,
    crl_file_name,
    read_anchors,
    thumbprint,
)

log = logging.getLogger(__name__)

TRUSTED, TRUSTED_CRLS, ISSUERS, ISSUER_CRLS, ALL = 1, 2, 4, 8, 15
MODE_WRITE_ERASE = MODE_WRITE | MODE_ERASE_EXISTING  # the one write mode a trust list opens with
MAX_SIZE = 4 * 1024 * 1024  # the server's MaxTrustListSize, bytes
MAX_READ = 1024 * 1024  # the most one Read returns (the TrustList's MaxByteStringLength)
ACTIVITY_TIMEOUT = 60.0  # seconds without a call on the TrustList before its handles are closed

_MARKER = "replace"  # in the update folder: the folders to replace, one a line; written last


@dataclass(frozen=True)
class TrustListContent:
    """The four lists as DER ByteStrings, and which of them a file specifies (TrustListMasks)."""

    trusted: tuple[bytes, ...] = ()
    trusted_crls: tuple[bytes, ...] = ()
    issuers: tuple[bytes, ...] = ()
    issuer_crls: tuple[bytes, ...] = ()
    specified: int = ALL

    def encode(self, masks: int = ALL) -> bytes:
        """The TrustListDataType of the lists ``masks`` names, OPC UA binary."""
        masks &= self.specified

        def part(bit: int, items: tuple[bytes, ...]) -> list[bytes] | None:
            return list(items) if masks & bit else None

        data = ua.TrustListDataType(
            SpecifiedLists=masks,
            TrustedCertificates=part(TRUSTED, self.trusted),
            TrustedCrls=part(TRUSTED_CRLS, self.trusted_crls),
            IssuerCertificates=part(ISSUERS, self.issuers),
            IssuerCrls=part(ISSUER_CRLS, self.issuer_crls),
        )
        encoded: bytes = struct_to_binary(data)
        return encoded

    @classmethod
    def decode(cls, data: bytes) -> TrustListContent:
        """The lists of a TrustListDataType; Bad_DecodingError when ``data`` is not exactly one, and
        Bad_InvalidArgument for SpecifiedLists outside TrustListMasks."""
        buffer = Buffer(data)
        try:
            value = struct_from_binary(ua.TrustListDataType, buffer)
        except (NotEnoughData, ValueError, TypeError, UnicodeDecodeError, OverflowError) as exc:
            raise CallError("BadDecodingError", f"the file is no TrustListDataType: {exc}") from None
        if len(buffer):
            raise CallError("BadDecodingError", f"{len(buffer)} bytes follow the TrustListDataType")
        masks = int(value.SpecifiedLists)
        if not 0 <= masks <= ALL:
            raise CallError("BadInvalidArgument", f"SpecifiedLists {masks} is not of TrustListMasks (0 to 15)")

        def part(bit: int, items: list[bytes] | None) -> tuple[bytes, ...]:
            return tuple(i or b"" for i in items or []) if masks & bit else ()

        return cls(
            part(TRUSTED, value.TrustedCertificates),
            part(TRUSTED_CRLS, value.TrustedCrls),
            part(ISSUERS, value.IssuerCertificates),
            part(ISSUER_CRLS, value.IssuerCrls),
            masks,
        )

    def merged_into(self, current: TrustListContent) -> TrustListContent:
        """``current`` with the lists this one specifies replaced (OPC 10000-12 7.8.2.5)."""
        s = self.specified
        return TrustListContent(
            self.trusted if s & TRUSTED else current.trusted,
            self.trusted_crls if s & TRUSTED_CRLS else current.trusted_crls,
            self.issuers if s & ISSUERS else current.issuers,
            self.issuer_crls if s & ISSUER_CRLS else current.issuer_crls,
        )


def update_lists(paths: PkiPaths, data: bytes, now: datetime) -> CheckedContent:
    """CloseAndUpdate's second half: ``data`` decoded, merged into the lists, checked and written."""
    update = TrustListContent.decode(data)
    checked = check_content(update.merged_into(read_content(paths)), now)
    write_content(paths, checked, update.specified)
    for warning in checked.warnings:
        log.warning("trust list: %s", warning)
    return checked


def read_content(paths: PkiPaths) -> TrustListContent:
    """The lists as the files under ``pki/`` hold them now (files that do not load are left out, as the
    checks of secure channels leave them out)."""
    anchors = read_anchors(paths)
    trusted, issuers = _unique(anchors.trusted), _unique(anchors.issuers)
    by_trusted = [c for c in anchors.crls if any(newest_crl(t, [c]) is not None for t in trusted)]
    return TrustListContent(
        tuple(der_of(c) for c in trusted),
        tuple(_crl_der(c) for c in by_trusted),
        tuple(der_of(c) for c in issuers),
        tuple(_crl_der(c) for c in anchors.crls if c not in by_trusted),
    )


@dataclass(frozen=True)
class CheckedContent:
    """A content that passed ``check_content``: what each folder is to hold."""

    trusted: tuple[x509.Certificate, ...]
    issuers: tuple[x509.Certificate, ...]
    crls: tuple[x509.CertificateRevocationList, ...]
    warnings: tuple[str, ...] = ()


def check_content(content: TrustListContent, now: datetime) -> CheckedContent:
    """The certificates and revocation lists of a whole new trust list, checked as OPC 10000-12 7.8.2.5
    asks (OPC 10000-4 6.1.3, the suppressible errors ignored but reported as warnings): each certificate
    DER, meeting the security policies (Bad_CertificatePolicyCheckFailed, decision 101) and signed by its
    issuer when the list holds it (Bad_CertificateInvalid), each issuer a CA
    (Bad_CertificateIssuerUseNotAllowed), each revocation list DER (Bad_CertificateInvalid) and signed by
    a CA of the list (Bad_CertificateChainIncomplete). A certificate outside its validity period is a
    warning. CallError for the first failure."""
    trusted = _parse_certificates(content.trusted, "TrustedCertificates")
    issuers = _parse_certificates(content.issuers, "IssuerCertificates")
    every = [*trusted, *issuers]
    warnings = []
    for cert in every:
        weak = policy_problem(cert)  # decision 101: what no channel would accept is not taken into the list
        if weak is not None:
            raise CallError("BadCertificatePolicyCheckFailed", weak)
        named = [c for c in every if c.subject == cert.issuer and c is not cert]
        if not is_self_signed(cert) and named and not any(issued_by(cert, c) for c in named):
            raise CallError("BadCertificateInvalid", f"{_label(cert)}: its issuer's signature does not verify")
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            warnings.append(f"{_label(cert)} is not valid now (until {cert.not_valid_after_utc:%Y-%m-%d})")
    for cert in issuers:
        if not may_sign_certificates(cert):
            why = f"IssuerCertificates: {_label(cert)} is not a CA that signs certificates"
            raise CallError("BadCertificateIssuerUseNotAllowed", why)
    crls: dict[bytes, x509.CertificateRevocationList] = {}  # the newest per CA
    for what, items in (("TrustedCrls", content.trusted_crls), ("IssuerCrls", content.issuer_crls)):
        for i, data in enumerate(items):
            try:
                crl = x509.load_der_x509_crl(data)
            except ValueError:
                raise CallError("BadCertificateInvalid", f"{what}[{i}] is not a DER revocation list") from None
            if not any(newest_crl(c, [crl]) is not None for c in every):
                why = f"{what}[{i}]: no CA of the trust list signed it (its issuer {crl.issuer.rfc4514_string()})"
                raise CallError("BadCertificateChainIncomplete", why)
            key = crl.issuer.public_bytes()
            if key not in crls or crls[key].last_update_utc < crl.last_update_utc:
                crls[key] = crl
    return CheckedContent(_unique(trusted), _unique(issuers), tuple(crls.values()), tuple(warnings))


def write_content(paths: PkiPaths, checked: CheckedContent, specified: int) -> None:
    """Replace the folders ``specified`` names with ``checked``'s content, so that a crash leaves either
    the old lists or (after ``finish_update``) the new ones."""
    folders: dict[Path, dict[str, bytes]] = {}
    if specified & TRUSTED:
        folders[paths.trusted] = {certificate_file_name(der_of(c)): der_of(c) for c in checked.trusted}
    if specified & ISSUERS:
        folders[paths.issuers] = {certificate_file_name(der_of(c)): der_of(c) for c in checked.issuers}
    if specified & (TRUSTED_CRLS | ISSUER_CRLS):
        folders[paths.crl] = {crl_file_name(c): _crl_der(c) for c in checked.crls}
    if not folders:
        return
    update = paths.trust_update
    shutil.rmtree(update, ignore_errors=True)
    for folder, files in folders.items():
        for name, data in files.items():
            atomic_write(update / folder.name / name, data, mode=0o644)
        (update / folder.name).mkdir(parents=True, exist_ok=True)
    atomic_write(update / _MARKER, "".join(f"{f.name}\n" for f in folders).encode(), mode=0o644)
    _apply(paths)
    for cert in checked.trusted:  # trusted now: no longer waiting in rejected/
        (paths.rejected / certificate_file_name(der_of(cert))).unlink(missing_ok=True)


def finish_update(paths: PkiPaths) -> bool:
    """Complete a replacement a crash cut short (True), or drop one that had not been written whole."""
    update = paths.trust_update
    if not update.exists():
        return False
    if not (update / _MARKER).is_file():
        shutil.rmtree(update, ignore_errors=True)
        return False
    _apply(paths)
    return True


def last_update(paths: PkiPaths) -> datetime:
    """When a list last changed (the latest change of the three folders): LastUpdateTime."""
    times = [f.stat().st_mtime for f in (paths.trusted, paths.issuers, paths.crl) if f.is_dir()]
    return datetime.fromtimestamp(max(times, default=0.0), UTC)


def _apply(paths: PkiPaths) -> None:
    update = paths.trust_update
    names = (update / _MARKER).read_text().split()
    for name in names:
        staged, folder = update / name, paths.root / name
        keep = {f.name for f in staged.iterdir()} if staged.is_dir() else set()
        for f in sorted(staged.iterdir()) if staged.is_dir() else []:
            atomic_write(folder / f.name, f.read_bytes(), mode=0o644)
        folder.mkdir(parents=True, exist_ok=True)
        for f in folder.iterdir():
            if f.is_file() and f.suffix.lower() in CERT_SUFFIXES | CRL_SUFFIXES and f.name not in keep:
                f.unlink()
        fsync_dir(folder)
    shutil.rmtree(update)
    fsync_dir(paths.root)
    log.info("trust list replaced: %s", ", ".join(f"{paths.root / n}/" for n in names))


# -- the file's handles --------------------------------------------------------------------------------


@dataclass
class _Handle:
    session: Hashable
    mode: int
    data: bytearray
    position: int = 0

    @property
    def writing(self) -> bool:
        return self.mode == MODE_WRITE_ERASE


@dataclass
class TrustListFile:
    """The open handles of one TrustList (module docstring). ``clock``: seconds, monotonic."""

    paths: PkiPaths
    max_size: int = MAX_SIZE
    max_read: int = MAX_READ
    activity_timeout: float = ACTIVITY_TIMEOUT
    clock: Callable[[], float] = time.monotonic
    _handles: dict[int, _Handle] = field(default_factory=dict)
    _next: int = 1
    _last_call: float = 0.0

    @property
    def open_count(self) -> int:
        return len(self._handles)

    def touch(self) -> int:
        """A call on the TrustList object: ``expire`` first, then the activity timeout starts again;
        returns how many handles expired."""
        closed = self.expire()
        self._last_call = self.clock()
        return closed

    def expire(self) -> int:
        """Close every handle when no call came for the activity timeout; returns how many."""
        if not self._handles or self.idle_for() <= self.activity_timeout:
            return 0
        closed = len(self._handles)
        self._handles.clear()
        log.warning("the trust list's %d open handle(s) closed: no call for %.0f s", closed, self.activity_timeout)
        return closed

    def idle_for(self) -> float:
        """Seconds since the last call on the TrustList object."""
        return self.clock() - self._last_call

    def refuse_changes(self) -> None:
        """AddCertificate and RemoveCertificate: Bad_InvalidState while the file is open (7.8.2.6)."""
        if self._handles:
            raise CallError("BadInvalidState", "the trust list is open; close it first")

    def open(self, session: Hashable, mode: int) -> int:
        if mode == MODE_READ:
            return self.open_with_masks(session, ALL)
        if mode != MODE_WRITE_ERASE:
            why = f"mode {mode}: a trust list opens for Read (1) or Write + EraseExisting (6)"
            raise CallError("BadNotSupported", why, argument=0)
        if self._handles:
            raise CallError("BadNotWritable", "the trust list is open; one writer and no reader may write it")
        return self._new(_Handle(session, mode, bytearray()))

    def open_with_masks(self, session: Hashable, masks: int) -> int:
        if not 0 <= masks <= ALL:
            raise CallError("BadInvalidArgument", f"masks {masks} is not of TrustListMasks (0 to 15)", argument=0)
        if any(h.writing for h in self._handles.values()):
            raise CallError("BadNotReadable", "the trust list is open for writing")
        return self._new(_Handle(session, MODE_READ, bytearray(read_content(self.paths).encode(masks))))

    def read(self, session: Hashable, handle: int, length: int) -> bytes:
        h = self._handle(session, handle)
        if length <= 0:
            raise CallError("BadInvalidArgument", "Length must be positive", argument=1)
        if h.writing:
            raise CallError("BadInvalidState", "the trust list was opened for writing")
        data = bytes(h.data[h.position : h.position + min(length, self.max_read)])
        h.position += len(data)
        return data

    def write(self, session: Hashable, handle: int, data: bytes) -> None:
        h = self._handle(session, handle)
        if not h.writing:
            raise CallError("BadInvalidState", "the trust list was opened for reading")
        end = h.position + len(data)
        if end > self.max_size:
            raise CallError("BadResourceUnavailable", f"a trust list holds at most {self.max_size} bytes")
        h.data[h.position : end] = data
        h.position = end

    def get_position(self, session: Hashable, handle: int) -> int:
        return self._handle(session, handle).position

    def set_position(self, session: Hashable, handle: int, position: int) -> None:
        h = self._handle(session, handle)
        h.position = min(position, len(h.data))  # past the end: the end (OPC 10000-20 4.2.7)

    def close(self, session: Hashable, handle: int) -> None:
        self._handle(session, handle)
        del self._handles[handle]

    def close_and_update(self, session: Hashable, handle: int, now: datetime) -> CheckedContent:
        """Close ``handle`` and replace the lists its content specifies; the content written, checked."""
        return update_lists(self.paths, self.close_written(session, handle), now)

    def close_written(self, session: Hashable, handle: int) -> bytes:
        """CloseAndUpdate's first half: the handle, opened for writing, closed; what was written."""
        h = self._handle(session, handle)
        if not h.writing:
            raise CallError("BadInvalidState", "CloseAndUpdate needs a trust list opened for writing")
        del self._handles[handle]  # closed, whatever follows
        return bytes(h.data)

    def close_session(self, session: Hashable) -> int:
        mine = [n for n, h in self._handles.items() if h.session == session]
        for n in mine:
            del self._handles[n]
        return len(mine)

    def _new(self, handle: _Handle) -> int:
        while self._next in self._handles or self._next == 0:
            self._next = self._next % 0xFFFFFFFF + 1
        number = self._next
        self._next = number % 0xFFFFFFFF + 1
        self._handles[number] = handle
        return number

    def _handle(self, session: Hashable, handle: int) -> _Handle:
        h = self._handles.get(handle)
        if h is None or h.session != session:
            raise CallError("BadInvalidArgument", f"invalid file handle {handle}", argument=0)
        return h


def _parse_certificates(items: Iterable[bytes], what: str) -> list[x509.Certificate]:
    found = []
    for i, data in enumerate(items):
        try:
            found.append(x509.load_der_x509_certificate(data))
        except ValueError:
            raise CallError("BadCertificateInvalid", f"{what}[{i}] is not a DER certificate") from None
    return found


def _unique(certs: Iterable[x509.Certificate]) -> tuple[x509.Certificate, ...]:
    return tuple({der_of(c): c for c in certs}.values())


def _label(cert: x509.Certificate) -> str:
    return f"{cert.subject.rfc4514_string()} ({thumbprint(der_of(cert))[:12]})"


def _crl_der(crl: x509.CertificateRevocationList) -> bytes:
    return crl.public_bytes(serialization.Encoding.DER)
