"""The user store (``<data_dir>/users.toml``) and the login throttle.

Passwords are kept only as argon2id hashes (argon2-cffi). The file is TOML, readable by an operator,
written atomically with mode 0600 by ``uacell user add/remove``; a running server picks up changes
on the next login. Pure apart from file I/O: no OPC UA stack here.
"""

from __future__ import annotations

import json
import logging
import os
import re
import tempfile
import threading
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

from uacell.roles import Role

_log = logging.getLogger(__name__)

USERS_FILE = "users.toml"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")


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


@dataclass(frozen=True)
class User:
    """A stored user (the hash never leaves this module through ``list``)."""

    name: str
    role: Role


class UserStore:
    """Users with roles and password hashes in one TOML file."""

    def __init__(self, path: Path, *, hasher: PasswordHasher | None = None) -> None:
        self.path = Path(path)
        self._hasher = hasher or PasswordHasher()
        self._entries: dict[str, tuple[Role, str]] = {}
        self._stamp: tuple[int, int] | None = None
        self._dummy_hash: str | None = None
        self._lock = threading.RLock()

    @classmethod
    def in_data_dir(cls, data_dir: Path, *, hasher: PasswordHasher | None = None) -> UserStore:
        return cls(Path(data_dir) / USERS_FILE, hasher=hasher)

    # reading ------------------------------------------------------------------------------------

    def _load(self) -> dict[str, tuple[Role, str]]:
        """The entries, re-read when the file changed (the CLI may edit it while the server runs)."""
        with self._lock:  # password checks run in worker threads
            return self._load_locked()

    def _load_locked(self) -> dict[str, tuple[Role, str]]:
        try:
            st = self.path.stat()
        except FileNotFoundError:
            self._entries, self._stamp = {}, None
            return self._entries
        stamp = (st.st_mtime_ns, st.st_size)
        if stamp != self._stamp:
            with self.path.open("rb") as f:
                data = tomllib.load(f)
            entries = {}
            for name, item in data.get("users", {}).items():
                try:
                    entries[validate_name(name)] = (Role.parse(item["role"]), str(item["hash"]))
                except (UserError, ValueError, KeyError, TypeError) as exc:
                    _log.error("%s: ignoring user %r: %s", self.path, name, exc)
            self._entries, self._stamp = entries, stamp
        return self._entries

    def list(self) -> list[User]:
        """All users, sorted by name."""
        return [User(n, r) for n, (r, _) in sorted(self._load().items())]

    def role_of(self, name: str) -> Role | None:
        entry = self._load().get(name)
        return entry[0] if entry else None

    def verify(self, name: str, password: str) -> Role | None:
        """The user's role when ``password`` is right, else None."""
        entry = self._load().get(name)
        if entry is None and self._dummy_hash is None:
            # Verifying unknown names against a hash keeps their timing like that of known names.
            self._dummy_hash = self._hasher.hash("uacell-no-such-user")
        stored = entry[1] if entry else (self._dummy_hash or "")
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
                entries[name] = (entry[0], fresh)
                self._save(entries)
        return entry[0]

    # writing ------------------------------------------------------------------------------------

    def add(self, name: str, role: Role | str, password: str) -> None:
        """Add ``name`` or replace its role and password."""
        validate_name(name)
        role = Role.parse(role)
        if not password:
            raise UserError("the password must not be empty")
        entries = dict(self._load())
        entries[name] = (role, self._hasher.hash(password))
        self._save(entries)

    def remove(self, name: str) -> None:
        entries = dict(self._load())
        if name not in entries:
            raise UserError(f"no user {name!r}")
        del entries[name]
        self._save(entries)

    def _save(self, entries: dict[str, tuple[Role, str]]) -> None:
        lines = [
            "# uacell users. Managed with `uacell user add|remove|list`.",
            "# Passwords are stored only as argon2id hashes.",
        ]
        for name, (role, hashed) in sorted(entries.items()):
            # JSON string escaping is valid TOML basic-string escaping for these ASCII values.
            lines += ["", f"[users.{json.dumps(name)}]", f"role = {json.dumps(role.label)}",
                      f"hash = {json.dumps(hashed)}"]
        atomic_write(self.path, ("\n".join(lines) + "\n").encode())
        self._stamp = None


def atomic_write(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Write ``data`` to ``path`` so readers see the old or the new file, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)


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


def _read_password(from_stdin: bool) -> str:
    """The new password: the first line of standard input, or typed twice at a prompt."""
    import getpass
    import sys

    if from_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    first = getpass.getpass("Password: ")
    if getpass.getpass("Repeat password: ") != first:
        raise UserError("the passwords do not match")
    return first


def run_user_command(args: Any, data_dir: Path) -> int:
    """``uacell user add|remove|list`` (args from uacell.cli); returns the exit status."""
    import sys

    store = UserStore.in_data_dir(Path(data_dir))
    try:
        if args.action == "add":
            validate_name(args.name)
            existed = store.role_of(args.name) is not None
            store.add(args.name, args.role, _read_password(args.password_stdin))
            print(f"{'updated' if existed else 'added'} user {args.name} ({args.role}) in {store.path}")
        elif args.action == "remove":
            store.remove(args.name)
            print(f"removed user {args.name} from {store.path}")
        elif args.action == "list":
            for user in store.list():
                print(f"{user.name}\t{user.role.label}")
        else:
            raise UserError(f"unknown action {args.action!r}")
    except (UserError, ValueError, OSError) as exc:
        print(f"uacell: {exc}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, EOFError):
        print("uacell: cancelled", file=sys.stderr)
        return 130
    return 0
