"""What every part of ``PackMLUnit`` shares (declared here, defined by the unit): the parts are
mixins split along the unit's responsibilities (``unit_view``, ``equipment_side``, ``unit_methods``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from datetime import datetime
from typing import TYPE_CHECKING, Any

from uacell.core.conditions import ConditionSet
from uacell.core.fsm import Reason, StateMachine
from uacell.models.tables import TransitionInfo
from uacell.packml.accounting import AdminAccounting
from uacell.packml.data import Admin, Status
from uacell.packml.equipment import PackMLEquipment
from uacell.packml.oee import OEE
from uacell.packml.types import PackMLAlarmDataType, PackMLDescriptorDataType


class UnitBase:
    """The attributes and internals of a ``PackMLUnit`` its parts use."""

    name: str
    status: Status
    admin: Admin
    accounting: AdminAccounting
    oee: OEE
    conditions: ConditionSet
    equipment: PackMLEquipment
    supported_modes: frozenset[int]
    machines: dict[str, StateMachine]
    base: StateMachine
    machine: StateMachine
    execute: StateMachine
    _steps: dict[str, list[tuple[str, str]]]
    _sc: dict[tuple[str, str], TransitionInfo]
    _executable_key: tuple[Any, ...] | None
    _executable_memo: dict[tuple[str | None, str], bool]
    _depth: int
    _pending: list[str | None]
    _clock: Callable[[], float]
    _wall: Callable[[], datetime]
    _reported_cur_mach_speed: float | None

    if TYPE_CHECKING:  # PackMLUnit's and UnitView's

        @property
        def state(self) -> str: ...

        @property
        def acting_state(self) -> str | None: ...

        def innermost(self) -> StateMachine: ...

        def _operation(
            self, changes: bool = True, touched: tuple[str, ...] | None = None
        ) -> contextlib.AbstractContextManager[None]: ...

        def _refusal(self, machine_name: str | None, method: str) -> str | None: ...

        def _check(self, machine_name: str | None, method: str) -> None: ...

        def _machine_command(
            self,
            machine_name: str | None,
            method: str,
            *,
            parameters: tuple[PackMLDescriptorDataType, ...] = (),
            reason: Reason = Reason.EXTERNAL,
            stop_reason: PackMLAlarmDataType | None = None,
        ) -> None: ...

        def _complete_now(self, state: str | None) -> bool: ...

        def _account(self) -> None: ...

        def _record_stop(self, reason: PackMLAlarmDataType) -> None: ...

        def _publish(self) -> None: ...

        def save(self) -> None: ...
