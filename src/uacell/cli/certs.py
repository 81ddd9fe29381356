"""``uacell cert list | trust ID | reject ID | remove ID | issuer FILE | crl FILE | renew | request |
install FILE``: the PKI of a data directory.

ID is a thumbprint (SHA-1, hex; its first characters are enough when they name one certificate) or a
certificate file. A running server reads ``pki/trusted/``, ``pki/issuers/`` and ``pki/crl/`` at every
channel and session, and within a second of a change closes the channels the files no longer admit
(decision 100), so trust changes apply without a restart; a renewed or installed server certificate is loaded at
the next start (``uacell.security.own_certificate``: a certificate from the plant's CA).
"""

from __future__ import annotations

import datetime as dt
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import NameOID

from uacell.config import Config
from uacell.core.files import atomic_write
from uacell.security.audit import AuditTrail
from uacell.security.chain import newest_crl, policy_problem
from uacell.security.own_certificate import InstallRefused, install_certificate, read_certificates, signing_request
from uacell.security.pki import (
    CERT_SUFFIXES,
    PkiPaths,
    RejectedLimit,
    TrustList,
    back_up,
    cert_to_der,
    crl_file_name,
    ensure_server_certificate,
    load_any_certificate,
    load_crl,
    revocation_lists,
    thumbprint,
)

MIN_PREFIX = 6
T = TypeVar("T")


class CertError(Exception):
    """The certificate a command names cannot be found or used."""


@dataclass(frozen=True)
class CertInfo:
    kind: str  # "own", "own-ca", "trusted", "issuer", "rejected"
    path: Path
    der: bytes
    subject: str
    application_uri: str
    not_before: dt.datetime
    not_after: dt.datetime

    @property
    def thumbprint(self) -> str:
        return thumbprint(self.der)

    def validity(self, now: dt.datetime | None = None) -> str:
        now = now or dt.datetime.now(dt.UTC)
        state = "expired" if now > self.not_after else "not yet valid" if now < self.not_before else "valid"
        return f"{state} {self.not_before:%Y-%m-%d} .. {self.not_after:%Y-%m-%d}"


def read_certificate(path: Path, kind: str = "file") -> CertInfo:
    """Load a DER or PEM certificate file; CertError when it is none."""
    return _info(kind, path, _read(path, load_any_certificate, "a certificate"))


def _read(path: Path, load: Callable[[bytes], T], what: str) -> T:
    """``load`` the file's bytes; CertError saying why when it cannot be read or is not ``what``."""
    try:
        return load(path.read_bytes())
    except OSError as exc:
        raise CertError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except ValueError as exc:
        raise CertError(f"{path} is not {what}: {exc}") from exc


def _info(kind: str, path: Path, cert: x509.Certificate) -> CertInfo:
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    subject = str(cns[0].value) if cns else cert.subject.rfc4514_string()
    return CertInfo(
        kind,
        path,
        cert_to_der(cert),
        subject,
        uris[0] if uris else "",
        cert.not_valid_before_utc,
        cert.not_valid_after_utc,
    )


def certificates(paths: PkiPaths) -> list[CertInfo]:
    """The own certificate, then trusted, issuer and rejected ones (unreadable files are skipped)."""
    found = []
    if paths.cert.is_file():
        try:
            found.append(read_certificate(paths.cert, "own"))
        except CertError:
            pass
    if paths.chain.is_file():  # the CA's certificates sent after the server's (decision 95)
        try:
            found += [_info("own-ca", paths.chain, c) for c in read_certificates(paths.chain.read_bytes())]
        except (OSError, ValueError):
            pass
    for kind, folder in (("trusted", paths.trusted), ("issuer", paths.issuers), ("rejected", paths.rejected)):
        if not folder.is_dir():
            continue
        for f in sorted(folder.iterdir()):
            if f.is_file() and f.suffix.lower() in CERT_SUFFIXES:
                try:
                    found.append(read_certificate(f, kind))
                except CertError:
                    continue
    return found


def find(paths: PkiPaths, ident: str, kinds: tuple[str, ...] = ("trusted", "issuer", "rejected")) -> list[CertInfo]:
    """The certificates ``ident`` names (a thumbprint prefix); several files may hold one certificate."""
    prefix = ident.strip().lower().replace(":", "")
    if len(prefix) < MIN_PREFIX or any(c not in "0123456789abcdef" for c in prefix):
        raise CertError(f"{ident!r} is neither a certificate file nor a thumbprint (at least {MIN_PREFIX} hex digits)")
    hits = [c for c in certificates(paths) if c.kind in kinds and c.thumbprint.startswith(prefix)]
    if not hits:
        raise CertError(f"no {' or '.join(kinds)} certificate has a thumbprint starting with {prefix}")
    if len({c.thumbprint for c in hits}) > 1:
        names = ", ".join(sorted({c.thumbprint for c in hits}))
        raise CertError(f"{prefix} names more than one certificate ({names}): give more digits")
    return hits


def _resolve(paths: PkiPaths, ident: str, kinds: tuple[str, ...]) -> list[CertInfo]:
    candidate = Path(ident).expanduser()
    if candidate.is_file():
        return [read_certificate(candidate)]
    return find(paths, ident, kinds)


def trust(paths: PkiPaths, ident: str, limit: RejectedLimit | None = None) -> Path:
    hits = _resolve(paths, ident, ("rejected", "trusted"))
    target = TrustList(paths, rejected_limit=limit).trust(hits[0].der)
    for c in hits:
        if c.kind == "rejected":
            c.path.unlink(missing_ok=True)
    return target


def reject(paths: PkiPaths, ident: str, limit: RejectedLimit | None = None) -> Path:
    hits = _resolve(paths, ident, ("trusted",))
    trusted = [c for c in hits if c.kind == "trusted"]
    if not trusted:
        raise CertError(f"{ident} is not trusted")
    target = TrustList(paths, rejected_limit=limit).reject(hits[0].der)
    for c in trusted:
        c.path.unlink(missing_ok=True)
    return target


def remove(paths: PkiPaths, ident: str) -> list[Path]:
    candidate = Path(ident).expanduser()
    if candidate.is_file():  # the certificate's own file: its copies in the folders go
        ident = read_certificate(candidate).thumbprint
    hits = find(paths, ident)
    for c in hits:
        c.path.unlink(missing_ok=True)
    return [c.path for c in hits]


def add_issuer(paths: PkiPaths, file: str) -> Path:
    """A CA's certificate into ``pki/issuers/``: it completes chains without being trusted itself."""
    info = read_certificate(Path(file).expanduser())
    cert = x509.load_der_x509_certificate(info.der)
    try:
        is_ca = cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    except x509.ExtensionNotFound:
        is_ca = False
    if not is_ca:
        raise CertError(f"{file} is not a CA's certificate (its BasicConstraints do not say CA)")
    paths.create()
    target = paths.issuers / f"{info.thumbprint}.der"
    atomic_write(target, info.der, mode=0o644)
    return target


def add_crl(paths: PkiPaths, file: str) -> Path:
    """A CA's revocation list into ``pki/crl/``, one file per CA (``<SHA-1 of the CA's name>.crl``): it
    must be signed by a CA in trusted/ or issuers/, and not be older than the list it replaces."""
    source = Path(file).expanduser()
    crl = _read(source, load_crl, "a revocation list")
    anchors = TrustList(paths).anchors()
    signer = next((c for c in (*anchors.trusted, *anchors.issuers) if newest_crl(c, [crl]) is not None), None)
    if signer is None:
        raise CertError(
            f"{source}: no CA in {paths.trusted}/ or {paths.issuers}/ signed it "
            f"(its issuer: {crl.issuer.rfc4514_string()}); add the CA's certificate first"
        )
    target = paths.crl / crl_file_name(crl)
    if target.exists():
        try:
            kept = load_crl(target.read_bytes())
        except ValueError:
            kept = None
        if kept is not None and kept.last_update_utc > crl.last_update_utc:
            raise CertError(f"{source} is older than the list kept in {target} ({kept.last_update_utc:%Y-%m-%d %H:%M})")
    atomic_write(target, crl.public_bytes(serialization.Encoding.DER), mode=0o644)
    return target


def renew(paths: PkiPaths, application_uri: str, hosts: list[str]) -> Path:
    """A new server certificate and key now; the old pair goes to ``pki/own/backup/``."""
    back_up(paths, move=True)
    cert, _ = ensure_server_certificate(paths, application_uri, hosts)
    return cert


def _print_list(paths: PkiPaths) -> None:
    infos = certificates(paths)
    print(f"{paths.root}: {len(infos) or 'no'} certificate{'' if len(infos) == 1 else 's'}")
    for c in infos:
        weak = policy_problem(x509.load_der_x509_certificate(c.der))
        note = f"  REFUSED BY THE SECURITY POLICIES: {weak}" if weak else ""  # decision 101
        print(f"{c.kind:8} {c.thumbprint}  {c.subject}  {c.application_uri or '-'}  {c.validity()}  {c.path}{note}")
    now = dt.datetime.now(dt.UTC)
    for path, crl in revocation_lists(paths):
        names = crl.issuer.get_attributes_for_oid(NameOID.COMMON_NAME)
        issuer = str(names[0].value) if names else crl.issuer.rfc4514_string()
        due = crl.next_update_utc
        until = f"{due:%Y-%m-%d}" if due else "-"
        state = "stale" if due is not None and due < now else "current"  # a stale list vouches for no chain
        print(f"crl      {issuer}  {len(crl)} revoked  {state} {crl.last_update_utc:%Y-%m-%d} .. {until}  {path}")


def run_cert_command(args: Any, config: Config) -> int:
    """``uacell cert ...`` (args from uacell.cli.main); returns the exit status."""
    paths = PkiPaths.in_data_dir(config.server.data_dir)
    cfg = config.server
    limit = RejectedLimit(cfg.rejected_max_files, cfg.rejected_max_age_days * 86400.0)  # as the server keeps it
    try:
        if args.action == "list":
            _print_list(paths)
            return 0
        if args.action == "trust":
            path = trust(paths, args.id, limit)
            print(f"trusted {path.stem}: {path}")
            weak = policy_problem(x509.load_der_x509_certificate(path.read_bytes()))
            if weak:
                print(
                    f"warning: the server refuses this certificate whatever the trust list says: {weak}",
                    file=sys.stderr,
                )
            detail: dict[str, Any] = {"thumbprint": path.stem, "file": str(path)}
        elif args.action == "reject":
            path = reject(paths, args.id, limit)
            print(f"rejected {path.stem}: {path}")
            detail = {"thumbprint": path.stem, "file": str(path)}
        elif args.action == "remove":
            removed = remove(paths, args.id)
            for p in removed:
                print(f"removed {p}")
            detail = {"files": [str(p) for p in removed]}
        elif args.action in ("issuer", "crl"):
            path = add_issuer(paths, args.file) if args.action == "issuer" else add_crl(paths, args.file)
            print(f"{'issuer' if args.action == 'issuer' else 'revocation list'} {path.stem}: {path}")
            detail = {"file": str(path), "from": str(args.file)}
        elif args.action == "request":
            request = signing_request(paths, cfg.application_uri, [cfg.host], new_key=args.new_key)
            if args.out:
                atomic_write(Path(args.out).expanduser(), request, mode=0o644)
                print(f"certificate signing request: {args.out}", file=sys.stderr)
            else:
                sys.stdout.write(request.decode())
            detail = {"new_key": args.new_key, "file": args.out or "-"}
        elif args.action == "install":
            source = Path(args.file).expanduser()
            done = install_certificate(paths, _read(source, bytes, "a file"), cfg.application_uri, [cfg.host])
            der = cert_to_der(done.certificate)
            print(
                f"server certificate {thumbprint(der)} from {done.certificate.issuer.rfc4514_string()}, "
                f"with {len(done.issuers)} CA certificate(s){' and its new key' if done.new_key else ''}: "
                f"{paths.cert} (used from the next start; the old pair is in {paths.backup})"
            )
            for warning in done.warnings:
                print(f"uacell: {warning}", file=sys.stderr)
            detail = {"thumbprint": thumbprint(der), "file": str(paths.cert), "from": str(source)}
        elif args.action == "renew":
            path = renew(paths, cfg.application_uri, [cfg.host])
            print(f"new server certificate {thumbprint(path.read_bytes())}: {path} (used from the next start)")
            detail = {"thumbprint": thumbprint(path.read_bytes()), "file": str(path)}
        else:
            raise CertError(f"unknown action {args.action!r}")
    except (CertError, InstallRefused, OSError) as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 1
    trail = AuditTrail.for_config(config)
    try:
        trail.record("cert", action=args.action, **detail)
    finally:
        trail.close()
    return 0
