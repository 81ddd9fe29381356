"""A PackML unit's own methods (PackMLBaseObjectType: SetUnitMode, SetMachSpeed, SetProduct,
SetParameter, RemoteCommand, SetInterlock; decisions 26, 27)."""

from __future__ import annotations

from collections.abc import Sequence

from uacell.core.errors import CallError
from uacell.packml.rules import UNIT
from uacell.packml.types import (
    PackMLDescriptorDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
    check_float,
    validate_descriptors,
    validate_products,
    validate_remote_interfaces,
)
from uacell.packml.unit_base import UnitBase


class UnitMethods(UnitBase):
    """The unit methods of ``PackMLUnit``: each checks, tells the equipment, then changes."""

    def check_unit_mode(self, mode: int) -> None:
        """Would SetUnitMode(``mode``) be accepted now (CallError if not)? Nothing changes."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in self.supported_modes:
            raise CallError(
                "BadInvalidArgument",
                f"RequestedMode {mode!r} is not a supported mode ({sorted(self.supported_modes)})",
                argument=0,
            )
        self._check(UNIT, "SetUnitMode")

    def set_unit_mode(self, mode: int) -> None:
        self.check_unit_mode(mode)
        with self._operation():
            s = self.status
            s.unit_mode_requested = s.unit_mode_change_in_process = True
            self._publish()  # clients may see the request in process before the new mode
            try:
                self.equipment.on_unit_mode(mode)
            finally:
                s.unit_mode_requested = s.unit_mode_change_in_process = False
            self._account()
            if s.unit_mode_current != mode:  # the same mode again is no change: current times keep running
                s.unit_mode_current = int(mode)
                self.accounting.new_mode()
            self.save()

    def set_mach_speed(self, speed: float) -> None:
        value = check_float(speed, "RequestedMachineSpeed", 0)
        low, high = self.status.mach_speed_range
        if not low <= value <= high:
            raise CallError(
                "BadInvalidArgument",
                f"RequestedMachineSpeed {value} is outside the EURange [{low}, {high}]",
                argument=0,
            )
        self.equipment.on_mach_speed(value)
        with self._operation(touched=("Status/MachSpeed",)):
            self.status.mach_speed = value

    def set_product(self, products: Sequence[PackMLProductDataType]) -> None:
        items = validate_products(list(products), argument=0, where="Product")
        self._check(UNIT, "SetProduct")
        self.equipment.on_product(items)
        with self._operation(touched=("Status/Product",)):
            self.status.product = items

    def set_parameter(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        items = validate_descriptors(list(parameters), argument=0, where="Parameter")
        self._check(UNIT, "SetParameter")
        self.equipment.on_parameter(items)
        with self._operation(touched=("Status/Parameter",)):
            self.status.parameter = items

    def remote_command(self, commands: Sequence[PackMLRemoteInterfaceDataType]) -> None:
        items = validate_remote_interfaces(list(commands), argument=0, where="RemoteInterface")
        self.equipment.on_remote_command(items)
        with self._operation(touched=("Status/RemoteParameter",)):
            self.status.remote_parameter = items

    def set_interlock(self, interlock_id: int, state: bool) -> None:
        """State true = interlocked: MaterialInterlock[id] becomes false (its bit means "ready")."""
        n = len(self.status.material_interlock)
        if isinstance(interlock_id, bool) or not isinstance(interlock_id, int) or not 0 <= interlock_id < n:
            raise CallError(
                "BadInvalidArgument",
                f"InterlockId {interlock_id!r} is not an index of MaterialInterlock (0..{n - 1})",
                argument=0,
            )
        if not isinstance(state, bool):
            raise CallError("BadInvalidArgument", f"State must be a Boolean, got {state!r}", argument=1)
        self.equipment.on_interlock(interlock_id, state)
        with self._operation():
            self.status.material_interlock[interlock_id] = not state
            self.status.material_interlocked = not all(self.status.material_interlock)
