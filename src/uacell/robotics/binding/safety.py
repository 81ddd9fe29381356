"""The robot's safety state from its controller (OPC 40010-1 SafetyStateType): for equipment that reports
it (``SafetyFeedback``), ``SafetyStates/<first>/ParameterSet`` OperationalMode, EmergencyStop and
ProtectiveStop follow the controller; Bad_NoCommunication while it is not known (docs/equipment.md)."""

from __future__ import annotations

import contextlib

from asyncua import ua

from uacell.core.capabilities import has, reachable
from uacell.robotics.binding.shared import ControllerBinding
from uacell.robotics.equipment import SafetyFeedback

_PARAMETERS = ("OperationalMode", "EmergencyStop", "ProtectiveStop")


class Safety:
    """The first SafetyState of the controller's robot, when its equipment reports safety."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding
        self.nodes: dict[str, ua.NodeId] = {}
        self._pending = False
        self._reachable = True

    async def setup(self) -> None:
        b = self.binding
        equipment = b.cell.equipment
        if not has(equipment, SafetyFeedback):
            return
        robot = b.controller.path.partition(".Controllers.")[0]
        states = [p for p in b.app.cell.built if p.path.startswith(f"{robot}.SafetyStates.")]
        if not states:
            return
        for name in _PARAMETERS:
            with contextlib.suppress(KeyError):
                self.nodes[name] = b.child(states[0].node, f"ParameterSet/{name}")
        equipment.add_safety_listener(self._changed)
        await self._write()

    def _changed(self) -> None:
        if not self._pending:
            self._pending = True
            self.binding.app.publisher.submit(self._write)

    async def _write(self) -> None:
        self._pending = False
        equipment = self.binding.cell.equipment
        assert has(equipment, SafetyFeedback)
        report = equipment.safety_report()
        values = self.binding.values
        if report is None or not reachable(equipment):
            bad = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
            for node in self.nodes.values():
                await values.write_status(node, bad)
            return
        written = {
            "OperationalMode": (report.operational_mode, ua.VariantType.Int32),
            "EmergencyStop": (report.emergency_stop, ua.VariantType.Boolean),
            "ProtectiveStop": (report.protective_stop, ua.VariantType.Boolean),
        }
        for name, node in self.nodes.items():
            value, vtype = written[name]
            await values.write(node, value, vtype)

    async def publish(self) -> None:
        reachable = bool(getattr(self.binding.cell.equipment, "reachable", True))
        if self.nodes and reachable != self._reachable:
            self._reachable = reachable
            await self._write()  # away: not its last values; back: its values now

    async def close(self) -> None:
        pass
