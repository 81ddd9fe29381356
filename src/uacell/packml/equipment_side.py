"""What a PackML unit's equipment reports through its ``UnitPort`` (packml/equipment.py): acting
states completed, its own commands, production counts, faults, warnings, alarms, its unit mode and
speeds, its conditions."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping

from uacell.core.errors import CallError
from uacell.core.fsm import Reason
from uacell.packml.data import push
from uacell.packml.rules import BASE, path
from uacell.packml.types import PackMLAlarmDataType
from uacell.packml.unit_base import UnitBase

log = logging.getLogger(__name__)


class EquipmentSide(UnitBase):
    """The equipment side of ``PackMLUnit`` (its ``UnitPort``)."""

    def state_complete(self, state: str | None = None) -> bool:
        """The running acting state (``state``, if given) is done: take its SC transition."""
        acting = self.acting_state
        if acting is None or (state is not None and state != acting):
            log.debug("%s: ignoring completion of %s (unit is %s)", self.name, state, self.state)
            return False
        if self._depth:
            self._pending.append(acting)  # called from inside a hook: take it once the hook returns
            return True
        with self._operation():
            return self._complete_now(acting)

    def path_to(self, state: str) -> list[tuple[str, str]]:
        """The fewest TR88 steps from the unit's innermost state to ``state`` (``path``): for equipment
        whose PLC moved on by itself (a gateway), to follow it there."""
        return path(self._steps, self.state, state)

    def state_numbered(self, number: int) -> str | None:
        """The TR88 state with StateNumber ``number`` (the NodeSet's numbers), if any."""
        for sm in self.machines.values():
            for name, info in sm.table.states.items():
                if info.number == number:
                    return name
        return None

    def equipment_command(self, method: str) -> None:
        """A transition the machine itself takes (same rules as for clients); innermost machine first."""
        for sm in reversed(self.base.walk()):
            if method in sm.table.methods and self._refusal(sm.name, method) is None:
                self._machine_command(sm.name, method, reason=Reason.SYSTEM)
                return
        raise CallError("BadInvalidState", f"{method} is not possible in {self.state}")

    def report_production(self, processed: int = 0, defective: int = 0, consumed: int | Mapping[int, int] = 0) -> None:
        with self._operation():
            if processed or defective:
                self._account()  # the spans up to now, before the counts
                self.oee.count(self._clock(), processed, defective)
            self.accounting.produce(processed, defective, consumed)

    def fault(self, alarm_id: int, message: str, *, value: int = 0, category: int = 1) -> None:
        with self._operation():
            alarm = PackMLAlarmDataType(alarm_id, value, message, category, self._wall(), None, True)
            push(self.admin.alarm, alarm, self.admin.alarm_extent)
            push(self.admin.alarm_history, alarm, self.admin.alarm_history_extent)
            log.warning("%s: fault %s: %s", self.name, alarm_id, message)
            if self._refusal(BASE, "Abort") is None:
                self._machine_command(BASE, "Abort", reason=Reason.ERROR, stop_reason=alarm)
            else:
                self._record_stop(alarm)

    def warning(self, warning_id: int, message: str, *, active: bool = True) -> None:
        with self._operation():
            w = self.admin.warning
            w[:] = [x for x in w if x.id != warning_id]
            if active:
                push(
                    w,
                    PackMLAlarmDataType(warning_id, 0, message, 0, self._wall(), None, True),
                    self.admin.warning_extent,
                )

    def equipment_unit_mode(self, mode: int) -> bool:
        """The equipment changed the unit mode by itself (a PLC's panel): take it as the current mode.
        A mode the unit does not support is refused (False, logged), nothing changes."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in self.supported_modes:
            log.warning("%s: the equipment reports unit mode %r, not a supported mode", self.name, mode)
            return False
        if mode == self.status.unit_mode_current:
            return True
        with self._operation():
            self._account()
            self.status.unit_mode_current = mode
            self.accounting.new_mode()
            self.save()
        return True

    def equipment_alarms(self, alarms: Mapping[int, str]) -> None:
        """The alarms the equipment has active now (ID -> message): Admin.Alarm becomes that list;
        an alarm that is new is also added to AlarmHistory, one that went is acknowledged there."""
        with self._operation():
            a = self.admin
            active = {x.id: x for x in a.alarm}
            if set(active) == set(alarms):
                return
            now = self._wall()
            gone = {(x.id, x.date_time) for x in a.alarm if x.id not in alarms}
            a.alarm_history[:] = [
                dataclasses.replace(h, ack_date_time=now, trigger=False) if (h.id, h.date_time) in gone else h
                for h in a.alarm_history
            ]
            a.alarm[:] = [x for x in a.alarm if x.id in alarms]
            for alarm_id, message in alarms.items():
                if alarm_id not in active:
                    alarm = PackMLAlarmDataType(alarm_id, 0, message, 1, now, None, True)
                    push(a.alarm, alarm, a.alarm_extent)
                    push(a.alarm_history, alarm, a.alarm_history_extent)

    def equipment_speeds(self, mach_speed: float | None = None, cur_mach_speed: float | None = None) -> None:
        """The equipment's own MachSpeed and CurMachSpeed (a PLC owns them): shown as reported, not
        checked against the EURange (the machine runs at what it runs at). A reported CurMachSpeed
        replaces the derived one (MachSpeed in Execute, else 0) from then on."""
        touched = ("Status/MachSpeed",) if mach_speed is not None else ()
        with self._operation(touched=touched):
            if mach_speed is not None:
                self.status.mach_speed = float(mach_speed)
            if cur_mach_speed is not None:
                self._reported_cur_mach_speed = float(cur_mach_speed)

    def equipment_condition(self, name: str, active: bool, message: str) -> None:
        """The equipment raises (``active``) or clears its condition ``name`` (one of its
        ``condition_names``)."""
        self.conditions.alarm(name, active, message)

    def set_blocked(self, blocked: bool) -> None:
        with self._operation():
            self.status.equipment_blocked = bool(blocked)

    def set_starved(self, starved: bool) -> None:
        with self._operation():
            self.status.equipment_starved = bool(starved)
