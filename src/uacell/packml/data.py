"""The values of a PackML unit (PackMLStatusObjectType, PackMLAdminObjectType) as plain data."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from uacell.packml.rules import Mode
from uacell.packml.types import (
    EUInformation,
    PackMLAlarmDataType,
    PackMLCountDataType,
    PackMLDescriptorDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
)

STATE_COLUMNS = 18  # StateCurrentTime/StateCumulativeTime second index: TR88 state numbers 0..17
INT32_WRAP = 2**31
PACKAGES = EUInformation("http://www.opcfoundation.org/UA/units/un/cefact", 5262926, "pkg", "package")


def i32(x: float) -> int:
    # Admin times and counts roll over at 2^31-1 (OPC 30050 §6.3.4).
    return int(x) % INT32_WRAP


@dataclass
class Status:
    """PackMLStatusObjectType values, plus uacell's StartParameters."""

    unit_mode_current: int = Mode.PRODUCE
    unit_mode_requested: bool = False
    unit_mode_change_in_process: bool = False
    state_requested: int = 0
    state_change_in_process: bool = False
    mach_speed: float = 0.0
    mach_speed_range: tuple[float, float] = (0.0, 600.0)
    cur_mach_speed: float = 0.0
    equipment_blocked: bool = False
    equipment_starved: bool = False
    material_interlocked: bool = False
    material_interlock: list[bool] = field(default_factory=list)
    parameter: tuple[PackMLDescriptorDataType, ...] = ()
    remote_parameter: tuple[PackMLRemoteInterfaceDataType, ...] = ()
    product: tuple[PackMLProductDataType, ...] = ()
    start_parameters: tuple[PackMLDescriptorDataType, ...] = ()


@dataclass
class Admin:
    """PackMLAdminObjectType values (times in whole seconds, Int32 with roll-over)."""

    parameter: tuple[PackMLDescriptorDataType, ...] = ()
    alarm: list[PackMLAlarmDataType] = field(default_factory=list)
    alarm_extent: int = 10
    alarm_history: list[PackMLAlarmDataType] = field(default_factory=list)
    alarm_history_extent: int = 50
    warning: list[PackMLAlarmDataType] = field(default_factory=list)
    warning_extent: int = 10
    stop_reason: PackMLAlarmDataType = field(default_factory=lambda: PackMLAlarmDataType(0))
    stop_reason_extent: int = 1
    mode_current_time: list[int] = field(default_factory=list)
    mode_cumulative_time: list[int] = field(default_factory=list)
    state_current_time: list[list[int]] = field(default_factory=list)
    state_cumulative_time: list[list[int]] = field(default_factory=list)
    prod_consumed_count: list[PackMLCountDataType] = field(default_factory=list)
    prod_processed_count: list[PackMLCountDataType] = field(default_factory=list)
    prod_defective_count: list[PackMLCountDataType] = field(default_factory=list)
    acc_time_since_reset: int = 0
    mach_design_speed: float = 0.0


def counted(c: PackMLCountDataType, n: int) -> PackMLCountDataType:
    return dataclasses.replace(c, count=i32(c.count + n), acc_count=i32(c.acc_count + n))


def push(items: list[PackMLAlarmDataType], item: PackMLAlarmDataType, extent: int) -> None:
    items.append(item)
    del items[: max(0, len(items) - extent)]
