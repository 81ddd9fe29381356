"""Reset Filler1, Start it with two parameters (PackMLDescriptorDataType[]), read back what it accepted, Stop.

Usage: python packml_start.py ENDPOINT   (an anonymous session: an operator on loopback)
"""

import asyncio
import sys

from asyncua import Client, Node, ua


async def wait_for(machine: Node, state: str) -> None:
    current = await machine.get_child("0:CurrentState")
    while (await current.read_value()).Text != state:
        await asyncio.sleep(0.05)


async def start(endpoint: str) -> None:
    async with Client(endpoint) as client:
        await client.load_data_type_definitions()  # makes ua.PackMLDescriptorDataType
        cell = await client.get_namespace_index("urn:uacell:cell")
        pml = await client.get_namespace_index("http://opcfoundation.org/UA/PackML/")
        machine = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState", cell))
        execute = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState.ExecuteState", cell))

        await machine.call_method(f"{pml}:Reset")  # Stopped -> Resetting -> Idle; a Bad status code raises
        print("Reset: Good")
        await wait_for(execute, "Idle")
        parameters = [
            ua.PackMLDescriptorDataType(
                ID=101, Name="FillVolume", Unit=ua.EUInformation(DisplayName=ua.LocalizedText("ml")), Value=250.5
            ),
            ua.PackMLDescriptorDataType(
                ID=102, Name="CapTorque", Unit=ua.EUInformation(DisplayName=ua.LocalizedText("N.m")), Value=2.25
            ),
        ]
        await execute.call_method(f"{pml}:Start", ua.Variant(parameters, ua.VariantType.ExtensionObject))
        print("Start: Good")
        await wait_for(execute, "Execute")
        accepted = await client.get_node(ua.NodeId("Filler1.Status.StartParameters", cell)).read_value()
        print("accepted:", [[p.ID, p.Name, p.Value] for p in accepted])
        await machine.call_method(f"{pml}:Stop")
        print("Stop: Good")


if __name__ == "__main__":
    asyncio.run(start(sys.argv[1]))
