"""SystemOperation: its machine (with the Idle and Executing sub-machines), methods and stop modes."""

from __future__ import annotations

from asyncua import ua

from uacell.robotics.binding.shared import ControllerBinding, Handler, executable
from uacell.robotics.companion import SYSTEM_OPERATION
from uacell.ua.context import Caller


class SystemOperationNodes:
    """The SystemOperation of one controller."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding

    @property
    def machine_node(self) -> ua.NodeId:
        b = self.binding
        return b.child(b.controller.node, "SystemOperation/SystemOperationStateMachine")

    async def setup(self) -> None:
        b = self.binding
        system = b.cell.system
        node = self.machine_node
        await b.bind_machine(node, system.machine)
        for machine, method in system.methods():
            b.bind_method(
                node, method, SYSTEM_OPERATION, self._handler(method),
                executable(system, machine, method), system.machine, b.controller.node,
            )  # fmt: skip
        await b.publish_stop_modes(node, system.possible_stop_modes, system.default_stop_mode)

    def _handler(self, method: str) -> Handler:
        system = self.binding.cell.system

        async def get_ready(caller: Caller) -> list[int]:
            return [await system.get_ready()]

        async def stand_down(caller: Caller) -> list[int]:
            return [await system.stand_down()]

        async def start(caller: Caller) -> list[int]:
            return [await system.start()]

        async def stop(caller: Caller, mode: int) -> list[int]:
            return [await system.stop(int(mode))]

        handlers: dict[str, Handler] = {"GetReady": get_ready, "StandDown": stand_down, "Start": start, "Stop": stop}
        return handlers[method]

    async def publish(self) -> None:
        pass

    async def close(self) -> None:
        pass
