"""DI LockingServices behaviour over the Controller1 > TaskControl1 tree (decision 20)."""

from __future__ import annotations

import pytest
from helpers import FakeClock

from uacell.core.errors import CallError
from uacell.di.locking import E_ALREADY_LOCKED, E_INVALID, E_NOT_LOCKED, OK, LockManager, LockOwner

A = LockOwner("session-a", "urn:client:a", "alice")
B = LockOwner("session-b", "urn:client:b", "bob")


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(100.0)


@pytest.fixture
def changes() -> list[object]:
    return []


@pytest.fixture
def locks(clock: FakeClock, changes: list[object]) -> LockManager:
    m = LockManager(10.0, clock=clock, on_change=changes.append)
    m.add("Controller1")
    m.add("TaskControl1", "Controller1")
    m.add("SystemOperation", "Controller1", lockable=False)
    m.add("Controller2")
    return m


def test_lock_blocks_other_sessions_only(locks: LockManager) -> None:
    assert locks.init_lock("TaskControl1", A, "maintenance") == OK
    assert locks.blocked_for("TaskControl1", "session-b")
    assert not locks.blocked_for("TaskControl1", "session-a")
    assert not locks.blocked_for("Controller1", "session-b")  # a lock covers downwards only
    with pytest.raises(CallError) as info:
        locks.check("TaskControl1", "session-b")
    assert info.value.status == "BadResourceUnavailable"
    assert "alice" in info.value.message
    locks.check("TaskControl1", "session-a")  # the owner passes


def test_controller_lock_covers_task_control_and_system_operation(locks: LockManager) -> None:
    assert locks.init_lock("Controller1", A) == OK
    for element in ("Controller1", "TaskControl1", "SystemOperation"):
        assert locks.blocked_for(element, "session-b")
        with pytest.raises(CallError, match="locked by alice"):
            locks.check(element, "session-b")
    assert not locks.blocked_for("Controller2", "session-b")


def test_status_variables(locks: LockManager, clock: FakeClock) -> None:
    assert locks.status("TaskControl1").locked is False
    locks.init_lock("TaskControl1", A)
    clock.now += 4
    st = locks.status("TaskControl1")
    assert (st.locked, st.locking_client, st.locking_user) == (True, "urn:client:a", "alice")
    assert st.remaining_ms == pytest.approx(6000.0)
    assert locks.status("Controller1").locked is False  # Locked tells about the element's own lock
    assert locks.max_inactive_ms == 10000.0


def test_init_lock_refused_when_locked_here_above_or_below(locks: LockManager) -> None:
    assert locks.init_lock("TaskControl1", A) == OK
    assert locks.init_lock("TaskControl1", B) == E_ALREADY_LOCKED
    assert locks.init_lock("TaskControl1", A) == E_ALREADY_LOCKED  # even for its own session
    assert locks.init_lock("Controller1", B) == E_ALREADY_LOCKED  # a descendant is locked by A
    assert locks.init_lock("Controller1", A) == OK  # A may widen its own lock
    assert locks.exit_lock("TaskControl1", "session-a") == OK
    assert locks.init_lock("TaskControl1", B) == E_ALREADY_LOCKED  # the ancestor is A's


def test_non_lockable_element(locks: LockManager) -> None:
    assert locks.init_lock("SystemOperation", A) == E_INVALID
    with pytest.raises(KeyError):
        locks.init_lock("Nowhere", A)


def test_exit_and_renew_by_owner_only(locks: LockManager, clock: FakeClock) -> None:
    assert locks.exit_lock("TaskControl1", "session-a") == E_NOT_LOCKED
    assert locks.renew_lock("TaskControl1", "session-a") == E_NOT_LOCKED
    locks.init_lock("TaskControl1", A)
    for call in (locks.exit_lock, locks.renew_lock):
        with pytest.raises(CallError) as info:
            call("TaskControl1", "session-b")
        assert info.value.status == "BadUserAccessDenied"
    assert locks.holder("TaskControl1") == A
    assert locks.exit_lock("TaskControl1", "session-a") == OK
    assert locks.holder("TaskControl1") is None
    assert not locks.blocked_for("TaskControl1", "session-b")


def test_break_lock(locks: LockManager) -> None:
    assert locks.break_lock("TaskControl1", "carol") == E_NOT_LOCKED
    locks.init_lock("TaskControl1", A)
    assert locks.break_lock("TaskControl1", "carol") == OK
    assert not locks.blocked_for("TaskControl1", "session-b")
    assert locks.init_lock("TaskControl1", B) == OK


def test_session_close_frees_its_locks_only(locks: LockManager) -> None:
    locks.init_lock("Controller1", A)
    locks.init_lock("Controller2", B)
    assert locks.session_closed("session-a") == ["Controller1"]
    assert not locks.blocked_for("TaskControl1", "session-b")
    assert locks.blocked_for("Controller2", "session-a")
    assert locks.session_closed("session-a") == []


def test_expiry_after_max_inactive_time(locks: LockManager, clock: FakeClock, changes: list[object]) -> None:
    locks.init_lock("TaskControl1", A)
    clock.now += 9.9
    assert locks.blocked_for("TaskControl1", "session-b")
    clock.now += 0.1
    assert not locks.blocked_for("TaskControl1", "session-b")  # computed lazily
    assert changes == ["TaskControl1", "TaskControl1"]  # locked, then expired


def test_periodic_expire_reports_freed_elements(locks: LockManager, clock: FakeClock) -> None:
    locks.init_lock("TaskControl1", A)
    locks.init_lock("Controller2", B)
    clock.now += 5
    locks.renew_lock("Controller2", "session-b")
    clock.now += 5
    assert locks.expire() == ["TaskControl1"]
    assert locks.locked_elements() == ["Controller2"]
    assert locks.status("Controller2").remaining_ms == pytest.approx(5000.0)


def test_owner_activity_renews_the_lock(locks: LockManager, clock: FakeClock) -> None:
    locks.init_lock("Controller1", A)
    clock.now += 8
    locks.check("TaskControl1", "session-a")  # the owner calls a method below its lock
    clock.now += 8
    assert locks.blocked_for("TaskControl1", "session-b")
    assert locks.status("Controller1").remaining_ms == pytest.approx(2000.0)
