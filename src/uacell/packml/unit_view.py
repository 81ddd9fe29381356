"""What a PackML unit shows: its states, which methods are executable now (decision 4), and every
Status/Admin value by browse path (``values``), OEE included."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from uacell.core.capabilities import reachable
from uacell.core.errors import CallError
from uacell.core.fsm import StateMachine
from uacell.packml.oee import Figures
from uacell.packml.publishing import TOUCHABLE, derived
from uacell.packml.rules import UNIT, UNIT_METHODS
from uacell.packml.unit_base import UnitBase


class UnitView(UnitBase):
    """The reading side of ``PackMLUnit``."""

    def now(self) -> float:
        return self._clock()

    def innermost(self) -> StateMachine:
        """The deepest active machine; its current state is the unit's TR88 state."""
        sm = self.base
        while (child := sm.hosted()) is not None:  # from the top down: the base is always active
            sm = child
        return sm

    @property
    def state(self) -> str:
        return self.innermost().current

    @property
    def state_number(self) -> int:
        sm = self.innermost()
        return sm.table.states[sm.current].number

    @property
    def states(self) -> tuple[str, str | None, str | None]:
        """(Base, Machine, Execute) current states, None for an inactive machine."""
        return (
            self.base.current,
            self.machine.current if self.machine.active else None,
            self.execute.current if self.execute.active else None,
        )

    @property
    def acting_state(self) -> str | None:
        """The acting state that is running (it ends when the equipment completes it), if any."""
        sm = self.innermost()
        return sm.current if (sm.name, sm.current) in self._sc else None

    @property
    def cur_mach_speed(self) -> float:
        return self.status.cur_mach_speed

    @property
    def unit_mode(self) -> int:
        return self.status.unit_mode_current

    @property
    def reachable(self) -> bool:
        """False while equipment that says so (a gateway driver's ``reachable``) cannot reach its PLC."""
        return reachable(getattr(self, "equipment", None))  # no equipment yet while the unit is being made

    def check_reachable(self) -> None:
        """Bad_CommunicationError while the equipment cannot reach its PLC: nothing is tried."""
        if not self.reachable:
            raise CallError("BadCommunicationError", f"{self.name}: the PLC cannot be reached")

    def check_command(self, machine_name: str | None, method: str) -> None:
        """Would ``method`` of ``machine_name`` be accepted now (CallError if not)? Nothing changes."""
        self.check_reachable()
        why = self._refusal(machine_name, method)
        if why is not None:
            if machine_name is not UNIT and (
                machine_name not in self.machines or method not in self.machines[machine_name].table.methods
            ):
                raise CallError("BadMethodInvalid", why)
            raise CallError("BadInvalidState", why)

    def executable(self, machine_name: str | None, method: str) -> bool:
        """True exactly when calling ``method`` now could succeed (decision 4)."""
        if not self.reachable:
            return False
        known = self._executable_now().get((machine_name, method))
        return known if known is not None else self._refusal(machine_name, method) is None

    @property
    def executable_inputs(self) -> tuple[Any, ...]:
        """Everything Executable of the unit's methods depends on: the three machines' states, the
        unit mode, the material interlocks and whether the equipment is reachable. The dispatcher
        re-evaluates the methods only when it changed."""
        s = self.status
        # The three machines' own current states decide which are active, hence the unit's state.
        return (
            self.base.current, self.machine.current, self.execute.current,
            s.unit_mode_current, bool(s.material_interlock), s.material_interlocked, self.reachable,
        )  # fmt: skip

    def _executable_now(self) -> dict[tuple[str | None, str], bool]:
        """Executable of every method, recomputed only when ``executable_inputs`` changed."""
        key = self.executable_inputs
        if key != self._executable_key:
            self._executable_memo = {k: self._refusal(*k) is None for k in self.methods()}
            self._executable_key = key
        return self._executable_memo

    def methods(self) -> list[tuple[str | None, str]]:
        """Every (machine_name, method) the unit offers; machine_name None for the unit's methods."""
        out: list[tuple[str | None, str]] = [(UNIT, m) for m in UNIT_METHODS]
        for sm in self.machines.values():
            out.extend((sm.name, m) for m in sorted(sm.table.methods))
        return out

    def values(self) -> dict[str, Any]:
        """Every Status/Admin value by browse path relative to the unit, plus ``Executable``."""
        s, a = self.status, self.admin
        # Fresh containers of immutable items: listeners may keep them without copying.
        return {
            "Status/UnitModeCurrent": s.unit_mode_current,
            "Status/UnitModeRequested": s.unit_mode_requested,
            "Status/UnitModeChangeInProcess": s.unit_mode_change_in_process,
            **derived(s),
            "Status/MachSpeed/EURange": s.mach_speed_range,
            "Status/CurMachSpeed/EURange": s.mach_speed_range,
            "Status/EquipmentBlocked": s.equipment_blocked,
            "Status/EquipmentStarved": s.equipment_starved,
            "Status/MaterialInterlocked": s.material_interlocked,
            "Status/MaterialInterlock": list(s.material_interlock),
            "Status/StartParameters": list(s.start_parameters),
            **{key: value(s) for key, value in TOUCHABLE.items()},
            "Admin/Parameter": list(a.parameter),
            "Admin/Alarm": list(a.alarm),
            "Admin/AlarmExtent": a.alarm_extent,
            "Admin/AlarmHistoryExtent": a.alarm_history_extent,
            "Admin/Warning": list(a.warning),
            "Admin/WarningExtent": a.warning_extent,
            "Admin/StopReasonExtent": a.stop_reason_extent,
            "Admin/MachDesignSpeed": a.mach_design_speed,
            **self.accounting.durable(),
            **self.accounting.times(),
            **self.oee_values(),
            # unreachable equipment (a gateway's PLC away): nothing is Executable
            "Executable": dict(self._executable_now()) if self.reachable else dict.fromkeys(self.methods(), False),
        }

    def oee_figures(self) -> Figures:
        """OEE over its window up to the last accounting (a transition, a count or a tick)."""
        last = self.accounting.last
        wall = self._wall() - timedelta(seconds=max(0.0, self._clock() - last))
        return self.oee.figures(last, wall)

    def oee_values(self) -> dict[str, float | int]:
        """The OEE variables under the unit (uacell's namespace), figures rounded to 3 decimals (0.1 %)."""
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in self.oee_figures().values().items()}
