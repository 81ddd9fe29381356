"""The user store (``<data_dir>/users.toml``) and the login throttle.

Passwords are kept only as argon2id hashes (argon2-cffi); a user may also log in with an X.509
certificate bound to them (decision 84), kept as the SHA-256 thumbprint of its DER encoding. The file
is TOML, readable by an operator, written atomically with mode 0600 by ``uacell user ...``; a running
server picks up changes on the next login, and its open sessions follow them (``grants``, decision 99). Pure
apart from file I/O: no OPC UA stack here.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import threading
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.hazmat.primitives.serialization import Encoding

from uacell.core.files import atomic_write
from uacell.core.roles import Role
from uacell.security.chain import key_problem

if TYPE_CHECKING:
    from uacell.config import Config

_log = logging.getLogger(__name__)

USERS_FILE = "users.toml"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")
_THUMBPRINT = re.compile(r"[0-9a-f]{64}")


class UserError(ValueError):
    """A user cannot be added or removed (bad name, unknown user, empty password...)."""


def validate_name(name: str) -> str:
    """Return ``name`` if it is a valid user name (1-64 of letters, digits, ``._@-``, not leading)."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise UserError(
            f"invalid user name {name!r}: use 1-64 letters, digits, '.', '_', '@' or '-', "
            "starting with a letter or digit"
        )
    return name


def check_password(password: str, min_length: int = 1) -> str:
    """Return ``password`` if it is long enough (``[users] min_password_length``)."""
    if not password:
        raise UserError("the password must not be empty")
    if len(password) < min_length:
        raise UserError(f"the password must have at least {min_length} characters")
    return password


def thumbprint(der: bytes) -> str:
    """How a certificate is kept and named: the SHA-256 of its DER encoding, 64 lowercase hex digits."""
    return hashlib.sha256(der).hexdigest()


def load_user_certificate(path: Path) -> bytes:
    """The DER encoding of the user certificate in ``path`` (DER or PEM), refused (UserError) unless it
    is an X.509 certificate with an RSA key of 2048 to 4096 bits: the signature every OPC UA security
    policy uacell offers asks a user to make (decisions 84 and 102)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else x509.load_der_x509_certificate(data)
    except ValueError:
        raise UserError(f"{path} holds no X.509 certificate (DER or PEM)") from None
    if not isinstance(cert.public_key(), rsa.RSAPublicKey):
        raise UserError(f"{path}: the certificate's key is not an RSA key (the security policies sign with RSA)")
    weak = key_problem(cert)
    if weak is not None:  # the server would refuse every login with it
        raise UserError(f"{path}: {weak}")
    return cert.public_bytes(Encoding.DER)


@dataclass(frozen=True)
class User:
    """A stored user (the hash never leaves this module through ``list``): whether they have a
    password, and the thumbprints of the certificates they may log in with."""

    name: str
    role: Role
    password: bool = True
    certificates: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Entry:
    role: Role
    hash: str  # "" for a user who logs in with a certificate only
    certificates: tuple[str, ...] = ()


class UserStore:
    """Users with roles and password hashes in one TOML file."""

    def __init__(self, path: Path, *, hasher: PasswordHasher | None = None) -> None:
        self.path = Path(path)
        self._hasher = hasher or PasswordHasher()
        self._entries: dict[str, _Entry] = {}
        self._stamp: tuple[int, int] | None = None
        self._by_certificate: dict[str, str] = {}  # thumbprint -> user name
        self._dummy_hash: str | None = None
        self._rehashed: dict[str, str] = {}  # a hash ``verify`` replaced -> its replacement (same password)
        self._lock = threading.RLock()

    @classmethod
    def in_data_dir(cls, data_dir: Path, *, hasher: PasswordHasher | None = None) -> UserStore:
        return cls(Path(data_dir) / USERS_FILE, hasher=hasher)

    # reading ------------------------------------------------------------------------------------

    def _load(self) -> dict[str, _Entry]:
        """The entries, re-read when the file changed (the CLI may edit it while the server runs)."""
        with self._lock:  # password checks run in worker threads
            return self._load_locked()

    def _load_locked(self) -> dict[str, _Entry]:
        try:
            st = self.path.stat()
        except FileNotFoundError:
            self._entries, self._stamp, self._by_certificate = {}, None, {}
            return self._entries
        stamp = (st.st_mtime_ns, st.st_size)
        if stamp != self._stamp:
            with self.path.open("rb") as f:
                data = tomllib.load(f)
            entries: dict[str, _Entry] = {}
            owners: dict[str, list[str]] = {}  # thumbprint -> the users it is bound to
            for name, item in data.get("users", {}).items():
                try:
                    entries[name] = _parse_entry(validate_name(name), item)
                except (UserError, ValueError, KeyError, TypeError) as exc:
                    _log.error("%s: ignoring user %r: %s", self.path, name, exc)
                    continue
                for thumb in entries[name].certificates:
                    owners.setdefault(thumb, []).append(name)
            for thumb, names in owners.items():
                if len(names) > 1:  # which user would it log in as? neither
                    _log.error("%s: certificate %s is bound to %s: nobody logs in with it", self.path, thumb, names)
            self._by_certificate = {thumb: names[0] for thumb, names in owners.items() if len(names) == 1}
            self._entries, self._stamp = entries, stamp
        return self._entries

    def list(self) -> list[User]:
        """All users, sorted by name."""
        return [User(n, e.role, bool(e.hash), e.certificates) for n, e in sorted(self._load().items())]

    def role_of(self, name: str) -> Role | None:
        entry = self._load().get(name)
        return entry.role if entry else None

    def user_of_certificate(self, der: bytes) -> tuple[str, Role] | None:
        """The user ``der`` is bound to, and their role; None for a certificate bound to nobody."""
        with self._lock:
            entries = self._load_locked()
            name = self._by_certificate.get(thumbprint(der))
        return (name, entries[name].role) if name is not None else None

    @property
    def stamp(self) -> tuple[int, int] | None:
        """What changes whenever the file is written (its modification time and size), None without it."""
        try:
            st = self.path.stat()
        except FileNotFoundError:
            return None
        return (st.st_mtime_ns, st.st_size)

    def password_hash(self, name: str) -> str:
        """The hash a password login of ``name`` is granted on now ("" for none): a session keeps it, and
        ``grants`` compares it with the file later."""
        entry = self._load().get(name)
        return entry.hash if entry else ""

    def grants(self, name: str, role: str, *, password_hash: str = "", certificate: str = "") -> bool:
        """Does the file still grant what a login of ``name`` as ``role`` was granted on (decision 99): the
        user is there with that role, and with that password (``password_hash``; a hash ``verify`` made
        again for the same password counts as the same) or with ``certificate`` (SHA-256) still bound?"""
        with self._lock:
            entry = self._load_locked().get(name)
            if entry is None or entry.role.label != role:
                return False
            if certificate:
                return self._by_certificate.get(certificate) == name
            current = password_hash
            while current in self._rehashed:
                current = self._rehashed[current]
            return bool(entry.hash) and current == entry.hash

    def verify(self, name: str, password: str) -> Role | None:
        """The user's role when ``password`` is right, else None."""
        entry = self._load().get(name)
        if entry is not None and not entry.hash:
            entry = None  # logs in with a certificate only
        if entry is None and self._dummy_hash is None:
            # Verifying unknown names against a hash keeps their timing like that of known names.
            self._dummy_hash = self._hasher.hash("uacell-no-such-user")
        stored = entry.hash if entry else (self._dummy_hash or "")
        try:
            self._hasher.verify(stored, password)
        except (VerificationError, InvalidHashError):
            return None
        if entry is None:
            return None
        if self._hasher.check_needs_rehash(stored):
            # Parameters were raised since this hash was made: store a fresh one.
            fresh = self._hasher.hash(password)
            with self._lock:
                entries = dict(self._load())
                entries[name] = replace(entries[name], hash=fresh)
                self._save(entries)
                self._rehashed[stored] = fresh  # the same password: its sessions keep their user
        return entry.role

    # writing ------------------------------------------------------------------------------------

    def add(
        self,
        name: str,
        role: Role | str,
        password: str | None,
        *,
        min_length: int = 1,
        certificate: bytes | None = None,
    ) -> None:
        """Add ``name`` with a password, a certificate (DER, ``load_user_certificate``) or both; refused
        (UserError) when the name exists: ``set_password``/``set_role``/``add_certificate`` change one."""
        validate_name(name)
        role = Role.parse(role)
        if password is None and certificate is None:
            raise UserError("a user needs a password or a certificate to log in with")
        if password is not None:
            check_password(password, min_length)
        entries = dict(self._load())
        if name in entries:
            raise UserError(f"user {name!r} exists (change it with 'uacell user passwd' or 'uacell user role')")
        certificates = (self._unbound(certificate, name),) if certificate is not None else ()
        entries[name] = _Entry(role, self._hasher.hash(password) if password is not None else "", certificates)
        self._save(entries)

    def set_password(self, name: str, password: str, *, min_length: int = 1) -> None:
        check_password(password, min_length)
        entries = dict(self._load())
        entries[name] = replace(self._existing(entries, name), hash=self._hasher.hash(password))
        self._save(entries)

    def set_role(self, name: str, role: Role | str) -> None:
        role = Role.parse(role)
        entries = dict(self._load())
        entries[name] = replace(self._existing(entries, name), role=role)
        self._save(entries)

    def add_certificate(self, name: str, der: bytes) -> str:
        """Let ``name`` log in with the certificate ``der``; returns its thumbprint. Refused when the
        certificate is bound to a user already (this one or another)."""
        entries = dict(self._load())
        entry = self._existing(entries, name)
        thumb = self._unbound(der, name)
        entries[name] = replace(entry, certificates=(*entry.certificates, thumb))
        self._save(entries)
        return thumb

    def remove_certificate(self, name: str, thumb: str) -> None:
        """Stop ``name`` logging in with the certificate of thumbprint ``thumb``; refused when it is not
        theirs, or is their only way to log in (remove the user instead, or give a password first)."""
        entries = dict(self._load())
        entry = self._existing(entries, name)
        if thumb not in entry.certificates:
            raise UserError(f"user {name!r} has no certificate {thumb}")
        left = tuple(t for t in entry.certificates if t != thumb)
        if not left and not entry.hash:
            raise UserError(
                f"it is the only way user {name!r} logs in: give a password first ('uacell user passwd') "
                "or remove the user"
            )
        entries[name] = replace(entry, certificates=left)
        self._save(entries)

    @staticmethod
    def _existing(entries: dict[str, _Entry], name: str) -> _Entry:
        if name not in entries:
            raise UserError(f"no user {name!r}")
        return entries[name]

    def _unbound(self, der: bytes, name: str) -> str:
        """The thumbprint of ``der``, refused when the certificate is bound to a user already."""
        thumb = thumbprint(der)
        for other, entry in self._load().items():
            if thumb in entry.certificates:
                whose = "this user" if other == name else f"user {other!r}"
                raise UserError(f"certificate {thumb} is bound to {whose} already")
        return thumb

    def remove(self, name: str) -> None:
        entries = dict(self._load())
        if name not in entries:
            raise UserError(f"no user {name!r}")
        del entries[name]
        self._save(entries)

    def _save(self, entries: dict[str, _Entry]) -> None:
        lines = [
            "# uacell users. Managed with `uacell user add|passwd|role|certificate|remove|list`.",
            "# Passwords are stored only as argon2id hashes, certificates as SHA-256 thumbprints of their DER.",
        ]
        for name, entry in sorted(entries.items()):
            # JSON string escaping is valid TOML basic-string escaping for these ASCII values.
            lines += ["", f"[users.{json.dumps(name)}]", f"role = {json.dumps(entry.role.label)}"]
            if entry.hash:
                lines.append(f"hash = {json.dumps(entry.hash)}")
            if entry.certificates:
                lines.append(f"certificates = {json.dumps(list(entry.certificates))}")
        atomic_write(self.path, ("\n".join(lines) + "\n").encode())
        self._stamp = None


def _parse_entry(name: str, item: Any) -> _Entry:
    """One user's table of the file; ValueError (or KeyError, TypeError) when it is not a usable one."""
    hashed = item.get("hash", "")
    certificates = item.get("certificates", [])
    if not isinstance(hashed, str) or not isinstance(certificates, list):
        raise ValueError("'hash' must be a string and 'certificates' a list")
    for thumb in certificates:
        if not isinstance(thumb, str) or not _THUMBPRINT.fullmatch(thumb):
            raise ValueError(f"certificate {thumb!r} is not a SHA-256 thumbprint (64 lowercase hex digits)")
    if not hashed and not certificates:
        raise ValueError("neither a password hash nor a certificate: the user cannot log in")
    return _Entry(Role.parse(item["role"]), hashed, tuple(dict.fromkeys(certificates)))


class LoginThrottle:
    """Slow down repeated login failures of one user name.

    Failures count per user name *at one address* and per user name *across all addresses*: after
    ``free`` failures in a row at one address (``free_per_user`` over all addresses, so that changing
    the source address does not help), each further failure makes the next attempt for that name wait
    ``base * 2**k`` seconds (capped at ``cap``); a success resets both. Anonymous logins and other user
    names, from the same address or not, are never delayed. Entries idle for ``forget_after`` seconds
    are forgotten, and at most ``max_entries`` are kept (a spray of names cannot exhaust memory).
    """

    def __init__(
        self,
        *,
        base: float = 1.0,
        cap: float = 30.0,
        free: int = 2,
        free_per_user: int = 10,
        forget_after: float = 900.0,
        max_entries: int = 10_000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.base, self.cap, self.free, self.free_per_user = base, cap, free, free_per_user
        self.forget_after, self.max_entries = forget_after, max_entries
        self._clock = clock
        # ("at", user, address) or ("user", user) -> (failures in a row, not before, last seen)
        self._failures: dict[tuple[str, ...], tuple[int, float, float]] = {}

    @staticmethod
    def _keys(user: str, address: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        return ("at", user, address), ("user", user)

    def wait_time(self, user: str, address: str) -> float:
        """Seconds before ``user`` may try again from ``address`` (0.0 when it may try now)."""
        self._forget_idle()
        now = self._clock()
        return max(
            (max(0.0, e[1] - now) for k in self._keys(user, address) if (e := self._failures.get(k))), default=0.0
        )

    def failed(self, user: str, address: str) -> float:
        """Record a failure; returns the delay now imposed on ``user`` at ``address``."""
        now = self._clock()
        if len(self._failures) >= self.max_entries:
            self._forget_idle(make_room=True)
        for key, free in zip(self._keys(user, address), (self.free, self.free_per_user), strict=True):
            count = self._failures.get(key, (0, now, now))[0] + 1
            excess = count - free
            delay = min(self.base * 2 ** min(excess - 1, 32), self.cap) if excess > 0 else 0.0
            self._failures[key] = (count, now + delay, now)
        delay = self.wait_time(user, address)
        if delay:
            _log.warning("failed logins of user %r (last from %s): next attempt in %.1f s", user, address, delay)
        return delay

    def succeeded(self, user: str, address: str) -> None:
        for key in self._keys(user, address):
            self._failures.pop(key, None)

    def _forget_idle(self, make_room: bool = False) -> None:
        now = self._clock()
        for key in [k for k, e in self._failures.items() if now - e[2] > self.forget_after]:
            del self._failures[key]
        if make_room and len(self._failures) >= self.max_entries:
            for key in sorted(self._failures, key=lambda k: self._failures[k][2])[: self.max_entries // 2]:
                del self._failures[key]


def _listed(user: User) -> str:
    """A line of ``uacell user list``: name and role, then how the user logs in when not by password only."""
    line = f"{user.name}\t{user.role.label}"
    if user.certificates:
        ways = ["password"] if user.password else []
        ways += [f"certificate {thumb}" for thumb in user.certificates]
        line += "\t" + ", ".join(ways)
    return line


def _thumbprint_of(given: str) -> str:
    """A certificate named on the command line: its thumbprint, or a file holding it."""
    if _THUMBPRINT.fullmatch(given.lower()):
        return given.lower()
    return thumbprint(load_user_certificate(Path(given)))


class NoTerminal(UserError):
    """The password cannot be asked for: no terminal and no --password-stdin."""


def _read_password(from_stdin: bool) -> str:
    """The new password: the first line of standard input, or typed twice at a prompt."""
    import getpass
    import sys

    if from_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    if not sys.stdin.isatty():
        raise NoTerminal("no terminal to ask for the password: give it on standard input with --password-stdin")
    first = getpass.getpass("Password: ")
    if getpass.getpass("Repeat password: ") != first:
        raise UserError("the passwords do not match")
    return first


def run_user_command(args: Any, config: Config) -> int:
    """``uacell user add|passwd|role|remove|list`` (args from uacell.cli.main); returns the exit status."""
    import sys

    from uacell.security.audit import AuditTrail

    store = UserStore.in_data_dir(config.server.data_dir)
    min_length = config.users.min_password_length
    trail: AuditTrail | None = None
    try:
        if args.action == "list":
            users = store.list()
            print(
                f"{store.path}: {len(users) or 'no'} user{'' if len(users) == 1 else 's'}"
                + ("" if store.path.exists() else " (the file does not exist)")
            )
            for user in users:
                print(_listed(user))
            return 0
        validate_name(args.name)
        details: dict[str, str] = {}
        if args.action == "add":
            if store.role_of(args.name) is not None:  # before asking for a password in vain
                raise UserError(
                    f"user {args.name!r} exists in {store.path} "
                    "(change it with 'uacell user passwd' or 'uacell user role')"
                )
            der = load_user_certificate(args.certificate) if args.certificate else None
            # With a certificate, a password only when one is given on standard input.
            password = _read_password(args.password_stdin) if der is None or args.password_stdin else None
            store.add(args.name, args.role, password, min_length=min_length, certificate=der)
            done = f"added user {args.name} ({args.role})"
            if der is not None:
                details["certificate"] = thumbprint(der)
                done += f", logging in with certificate {thumbprint(der)}" + (" or a password" if password else "")
        elif args.action == "certificate":
            if args.remove:
                thumb = _thumbprint_of(args.certificate)
                store.remove_certificate(args.name, thumb)
                done = f"user {args.name} no longer logs in with certificate {thumb}"
            else:
                thumb = store.add_certificate(args.name, load_user_certificate(args.certificate))
                done = f"user {args.name} may log in with certificate {thumb}"
            details = {"certificate": thumb}
        elif args.action == "passwd":
            if store.role_of(args.name) is None:
                raise UserError(f"no user {args.name!r} in {store.path}")
            store.set_password(args.name, _read_password(args.password_stdin), min_length=min_length)
            done = f"changed the password of user {args.name}"
        elif args.action == "role":
            store.set_role(args.name, args.role)
            done = f"changed the role of user {args.name} to {args.role}"
        elif args.action == "remove":
            store.remove(args.name)
            done = f"removed user {args.name}"
        else:
            raise UserError(f"unknown action {args.action!r}")
        print(f"{done} in {store.path}")
        trail = AuditTrail.for_config(config)
        trail.record(
            "user",
            action="certificate_remove" if getattr(args, "remove", False) else args.action,
            user=args.name,
            role=getattr(args, "role", None),
            file=str(store.path),
            **details,
        )
    except NoTerminal as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 2
    except (UserError, ValueError, OSError) as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, EOFError):
        print("uacell: cancelled", file=sys.stderr)
        return 130
    finally:
        if trail is not None:
            trail.close()
    return 0
