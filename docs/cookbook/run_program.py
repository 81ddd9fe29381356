"""Power up Robot1, load a program by name, start it, then stop it with a stop mode the controller offers.

Usage: python run_program.py ENDPOINT PROGRAM   (an anonymous session: an operator on loopback)
"""

import asyncio
import sys

from asyncua import Client, Node, ua

CONTROLLER = "Robot1.Controllers.Controller1"
TASK_CONTROL = f"{CONTROLLER}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SYSTEM = f"{CONTROLLER}.SystemOperation.SystemOperationStateMachine"


async def wait_for(machine: Node, state: str) -> None:
    current = await machine.get_child("0:CurrentState")
    while (await current.read_value()).Text != state:
        await asyncio.sleep(0.05)


async def run(endpoint: str, program: str) -> None:
    async with Client(endpoint) as client:
        cell = await client.get_namespace_index("urn:uacell:cell")
        rob = await client.get_namespace_index("http://opcfoundation.org/UA/Robotics/")
        system = client.get_node(ua.NodeId(SYSTEM, cell))
        task = client.get_node(ua.NodeId(TASK_CONTROL, cell))

        # PossibleStopModes: EnumValueType[], each Value (Int64) a mode Stop takes, with its name.
        modes = {
            m.DisplayName.Text: m.Value for m in await (await task.get_child(f"{rob}:PossibleStopModes")).read_value()
        }
        default = await (await task.get_child(f"{rob}:ConfiguredDefaultStopMode")).read_value()
        print("stop modes:", modes, "default:", default)

        print("GetReady:", await system.call_method(f"{rob}:GetReady"))  # every method answers a Status (0 = OK)
        await wait_for(system, "Ready")
        print("LoadByName:", await task.call_method(f"{rob}:LoadByName", program))  # the file name without .robot
        print("Start:", await task.call_method(f"{rob}:Start"))
        await wait_for(task, "Executing")
        mode = ua.Variant(modes.get("QuickStop", 0), ua.VariantType.Int64)  # 0: the ConfiguredDefaultStopMode
        print("Stop:", await task.call_method(f"{rob}:Stop", mode))
        await wait_for(task, "Ready")  # Ready/Suspended: Start resumes, ResetToProgramStart rewinds
        print("UnloadProgram:", await task.call_method(f"{rob}:UnloadProgram"))
        print("StandDown:", await system.call_method(f"{rob}:StandDown"))


if __name__ == "__main__":
    asyncio.run(run(sys.argv[1], sys.argv[2]))
