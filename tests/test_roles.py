"""The role table and the listening policy."""

from __future__ import annotations

import pytest

from uacell.catalog import companions
from uacell.core.rights import RoleTable
from uacell.core.roles import (
    Role,
    anonymous_role,
    is_loopback,
    listening_policy,
    may,
    none_security_allowed,
)
from uacell.robotics.companion import SYSTEM_OPERATION

TABLE = RoleTable(companions())
may_call, required_role = TABLE.may_call, TABLE.required_role


def test_roles_are_ordered_and_parse_from_names() -> None:
    assert Role.OBSERVER < Role.OPERATOR < Role.ENGINEER < Role.ADMIN
    assert Role.parse("Engineer") is Role.ENGINEER
    assert Role.ADMIN.label == "admin"
    with pytest.raises(ValueError, match="observer, operator, engineer, admin"):
        Role.parse("root")


@pytest.mark.parametrize(
    ("method", "hint", "role"),
    [
        ("LoadByName", "TaskControlStateMachineType", Role.OPERATOR),
        ("3:ResetToProgramStart", "3:ReadySubstateMachineType", Role.OPERATOR),
        ("GetReady", SYSTEM_OPERATION, Role.OPERATOR),
        ("Start", "PackMLMachineStateMachineType", Role.OPERATOR),
        ("SetMachSpeed", "PackMLBaseObjectType", Role.OPERATOR),
        ("SetUnitMode", "PackMLBaseObjectType", Role.OPERATOR),
        ("SetProduct", "PackMLBaseObjectType", Role.ENGINEER),
        ("SetParameter", "PackML", Role.ENGINEER),
        ("InitLock", "LockingServicesType", Role.OPERATOR),
        ("BreakLock", "LockingServicesType", Role.ENGINEER),
        ("Read", "FileType", Role.OPERATOR),
        ("Write", "FileType", Role.ENGINEER),
        ("CreateFile", "FileDirectoryType", Role.ENGINEER),
        ("Delete", "Programs", Role.ENGINEER),
        ("Acknowledge", "AlarmConditionType", Role.OPERATOR),
        ("Disable", "AlarmConditionType", Role.ENGINEER),
        # Deny by default: unknown methods and unknown object types are admin only.
        ("Reboot", "TaskControlStateMachineType", Role.ADMIN),
        ("Start", "SomeVendorType", Role.ADMIN),
    ],
)
def test_required_role(method: str, hint: str, role: Role) -> None:
    assert required_role(method, hint) is role


def test_file_open_depends_on_mode() -> None:
    assert required_role("Open", "FileType", file_mode=1) is Role.OPERATOR  # Read
    for mode in (2, 3, 1 | 4, 1 | 8):  # Write, Read+Write, EraseExisting, Append
        assert required_role("Open", "FileType", file_mode=mode) is Role.ENGINEER
    assert required_role("Open", "FileType") is Role.ENGINEER  # mode unknown: assume writing


def test_role_method_matrix() -> None:
    for (family, method), least in TABLE.method_roles.items():
        for role in Role:
            assert may_call(role, method, family, file_mode=1) is (role >= least), (role, family, method)


def test_service_actions() -> None:
    assert may(Role.OBSERVER, "read") and may(Role.OBSERVER, "subscribe") and may(Role.OBSERVER, "browse")
    assert not may(Role.OPERATOR, "write")
    assert may(Role.ENGINEER, "write")
    assert not may(Role.ENGINEER, "add_nodes") and may(Role.ADMIN, "add_nodes")


@pytest.mark.parametrize(
    ("host", "loop"),
    [
        ("127.0.0.1", True),
        ("127.1.2.3", True),
        ("::1", True),
        ("[::1]", True),
        ("localhost", True),
        ("LOCALHOST.", True),
        ("0.0.0.0", False),
        ("::", False),
        ("", False),
        ("192.168.0.5", False),
        ("plc.example", False),
    ],
)
def test_is_loopback(host: str, loop: bool) -> None:
    assert is_loopback(host) is loop


def test_anonymous_and_none_security_follow_the_listening_hosts() -> None:
    assert anonymous_role(["127.0.0.1", "::1"]) is Role.OPERATOR
    assert anonymous_role(["127.0.0.1", "10.0.0.7"]) is Role.OBSERVER
    assert anonymous_role([]) is Role.OBSERVER
    assert anonymous_role(["0.0.0.0"], Role.ADMIN) is Role.ADMIN
    assert none_security_allowed(["localhost"]) is True
    assert none_security_allowed(["0.0.0.0"]) is False
    assert none_security_allowed(["0.0.0.0"], True) is True
    assert none_security_allowed(["127.0.0.1"], False) is False


def test_listening_policy_warns_only_about_deviations() -> None:
    plain = listening_policy(["127.0.0.1"])
    assert (plain.anonymous_role, plain.none_security, plain.warnings) == (Role.OPERATOR, True, [])
    same = listening_policy(["10.0.0.7"], anonymous=Role.OBSERVER, allow_none_security=False)
    assert same.warnings == []
    loose = listening_policy(["10.0.0.7"], anonymous=Role.OPERATOR, allow_none_security=True)
    assert (loose.anonymous_role, loose.none_security) == (Role.OPERATOR, True)
    assert len(loose.warnings) == 2
    assert "operator" in loose.warnings[0] and "non-loopback" in loose.warnings[0]
    assert "None is offered" in loose.warnings[1]
