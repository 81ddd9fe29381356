"""The user store and the login throttle."""

from __future__ import annotations

import os
import stat
import tomllib
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from helpers import FakeClock

from uacell.core.roles import Role
from uacell.security.users import LoginThrottle, User, UserError, UserStore, thumbprint, validate_name

# Cheap argon2 parameters keep the tests fast; the real store uses argon2-cffi's defaults.
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)


@pytest.fixture
def store(tmp_path: Path) -> UserStore:
    return UserStore.in_data_dir(tmp_path, hasher=FAST)


def test_add_verify_list_remove(store: UserStore) -> None:
    store.add("alice", "operator", "s3cret")
    store.add("bob", Role.ENGINEER, "hunter2")
    assert store.verify("alice", "s3cret") is Role.OPERATOR
    assert store.verify("alice", "wrong") is None
    assert store.verify("nobody", "s3cret") is None
    assert store.list() == [User("alice", Role.OPERATOR), User("bob", Role.ENGINEER)]
    store.remove("alice")
    assert store.verify("alice", "s3cret") is None
    assert [u.name for u in store.list()] == ["bob"]
    with pytest.raises(UserError, match="no user 'alice'"):
        store.remove("alice")


def test_add_refuses_an_existing_name_and_passwd_role_change_one_thing(store: UserStore) -> None:
    store.add("alice", "operator", "one")
    before = store.path.read_bytes()
    with pytest.raises(UserError, match="'alice' exists"):
        store.add("alice", "admin", "two")
    assert store.path.read_bytes() == before
    store.set_password("alice", "two")
    assert store.verify("alice", "one") is None
    assert store.verify("alice", "two") is Role.OPERATOR
    store.set_role("alice", "admin")
    assert store.verify("alice", "two") is Role.ADMIN
    with pytest.raises(UserError, match="no user 'bob'"):
        store.set_password("bob", "x")
    with pytest.raises(UserError, match="no user 'bob'"):
        store.set_role("bob", "admin")


def test_minimum_password_length(store: UserStore) -> None:
    with pytest.raises(UserError, match="at least 8 characters"):
        store.add("alice", "operator", "short", min_length=8)
    assert store.list() == []
    store.add("alice", "operator", "long enough", min_length=8)
    with pytest.raises(UserError, match="at least 12 characters"):
        store.set_password("alice", "still short", min_length=12)
    assert store.verify("alice", "long enough") is Role.OPERATOR


def test_file_holds_only_hashes_and_is_private(store: UserStore) -> None:
    store.add("alice", "observer", "plain-text-password")
    text = store.path.read_text()
    assert "plain-text-password" not in text
    data = tomllib.loads(text)
    assert data["users"]["alice"]["role"] == "observer"
    assert data["users"]["alice"]["hash"].startswith("$argon2id$")
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600
    assert [p.name for p in store.path.parent.iterdir()] == ["users.toml"]  # no temp file left


def test_store_sees_changes_made_by_another_process(tmp_path: Path) -> None:
    server = UserStore.in_data_dir(tmp_path, hasher=FAST)
    assert server.verify("carol", "pw") is None
    cli = UserStore.in_data_dir(tmp_path, hasher=FAST)
    cli.add("carol", "engineer", "pw")
    assert server.verify("carol", "pw") is Role.ENGINEER


def test_bad_entries_in_file_are_skipped(tmp_path: Path) -> None:
    store = UserStore.in_data_dir(tmp_path, hasher=FAST)
    store.add("ok", "operator", "pw")
    with store.path.open("a") as f:
        f.write('\n[users."bad name"]\nrole = "operator"\nhash = "x"\n')
        f.write('[users.eve]\nrole = "god"\nhash = "x"\n')
    os.utime(store.path, ns=(1, 1))  # make sure the store notices the change
    assert [u.name for u in store.list()] == ["ok"]


def test_outdated_hash_is_upgraded_on_login(tmp_path: Path) -> None:
    UserStore.in_data_dir(tmp_path, hasher=FAST).add("dave", "operator", "pw")
    stronger = PasswordHasher(time_cost=2, memory_cost=128, parallelism=1)
    store = UserStore.in_data_dir(tmp_path, hasher=stronger)
    assert store.verify("dave", "pw") is Role.OPERATOR
    stored = tomllib.loads(store.path.read_text())["users"]["dave"]["hash"]
    assert "t=2" in stored and not stronger.check_needs_rehash(stored)


def test_what_a_login_was_granted_on_is_compared_with_the_file(tmp_path: Path) -> None:
    """Decision 99: a session's login still holds while the file grants the same user the same role and
    the same password (a hash remade on login for the same password included) or the same certificate."""
    cli = UserStore.in_data_dir(tmp_path, hasher=FAST)  # `uacell user`, another process
    cli.add("dave", "operator", "pw-1")
    cli.add("erin", "engineer", None, certificate=b"erin's badge")
    stronger = PasswordHasher(time_cost=2, memory_cost=128, parallelism=1)
    server = UserStore.in_data_dir(tmp_path, hasher=stronger)
    before = server.password_hash("dave")
    badge = thumbprint(b"erin's badge")
    assert server.grants("dave", "operator", password_hash=before)
    assert server.grants("erin", "engineer", certificate=badge)
    assert server.verify("dave", "pw-1") is Role.OPERATOR  # remade with the stronger parameters
    assert server.password_hash("dave") != before
    assert server.grants("dave", "operator", password_hash=before)  # the same password
    assert server.grants("dave", "operator", password_hash=server.password_hash("dave"))
    assert not server.grants("dave", "engineer", password_hash=before)  # not the role it was given
    assert not server.grants("dave", "operator", password_hash="")
    assert not server.grants("erin", "engineer", password_hash=server.password_hash("erin"))  # no password
    cli.set_password("dave", "pw-2")
    assert not server.grants("dave", "operator", password_hash=before)
    cli.add_certificate("erin", b"erin's new badge")
    assert server.grants("erin", "engineer", certificate=badge)  # still bound
    cli.remove_certificate("erin", badge)
    assert not server.grants("erin", "engineer", certificate=badge)
    cli.remove("dave")
    assert not server.grants("dave", "operator", password_hash=server.password_hash("dave"))


@pytest.mark.parametrize("name", ["alice", "a.b-c_d@plant", "X", "7" * 64])
def test_valid_names(name: str) -> None:
    assert validate_name(name) == name


@pytest.mark.parametrize("name", ["", ".hidden", "-x", "with space", "a/b", 'q"uote', "é", "7" * 65, "a\nb"])
def test_invalid_names(store: UserStore, name: str) -> None:
    with pytest.raises(UserError, match="invalid user name"):
        store.add(name, "operator", "pw")


def test_empty_password_and_unknown_role_are_refused(store: UserStore) -> None:
    with pytest.raises(UserError, match="empty"):
        store.add("alice", "operator", "")
    with pytest.raises(ValueError, match="unknown role"):
        store.add("alice", "superuser", "pw")
    assert store.list() == []


def test_throttle_grows_exponentially_to_a_cap_and_resets() -> None:
    clock = FakeClock(0.0)
    t = LoginThrottle(base=1.0, cap=8.0, free=2, clock=clock)
    assert t.wait_time("alice", "10.0.0.9") == 0.0
    delays = [t.failed("alice", "10.0.0.9") for _ in range(7)]
    assert delays == [0.0, 0.0, 1.0, 2.0, 4.0, 8.0, 8.0]
    assert t.wait_time("alice", "10.0.0.9") == 8.0
    assert t.wait_time("bob", "10.0.0.9") == 0.0  # other users are not affected
    clock.now += 5
    assert t.wait_time("alice", "10.0.0.9") == 3.0
    t.succeeded("alice", "10.0.0.9")
    assert t.wait_time("alice", "10.0.0.9") == 0.0
    assert t.failed("alice", "10.0.0.9") == 0.0  # counting starts afresh


def test_throttle_forgets_idle_addresses() -> None:
    clock = FakeClock(0.0)
    t = LoginThrottle(base=1.0, cap=30.0, free=0, forget_after=60.0, clock=clock)
    t.failed("alice", "a")
    t.failed("alice", "a")
    clock.now += 61
    assert t.wait_time("alice", "a") == 0.0
    assert t.failed("alice", "a") == 1.0  # a first failure again
