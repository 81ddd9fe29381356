"""Take Controller1's DI lock, see who holds it, release it (OPC 10000-100 LockingServices).

Usage: python lock.py ENDPOINT   (an anonymous session: an operator on loopback)
"""

import asyncio
import sys

from asyncua import Client, ua


async def lock(endpoint: str) -> None:
    async with Client(endpoint) as client:
        cell = await client.get_namespace_index("urn:uacell:cell")
        di = await client.get_namespace_index("http://opcfoundation.org/UA/DI/")
        lock = client.get_node(ua.NodeId("Robot1.Controllers.Controller1.Lock", cell))

        print("InitLock:", await lock.call_method(f"{di}:InitLock", "cookbook"))  # 0: yours now (Context: any text)
        print("Locked:", await (await lock.get_child(f"{di}:Locked")).read_value())
        print("LockingClient:", await (await lock.get_child(f"{di}:LockingClient")).read_value())
        # While it is held, other sessions' calls on the controller and its task controls answer
        # Bad_ResourceUnavailable; RenewLock before RemainingLockTime runs out keeps it.
        print("ExitLock:", await lock.call_method(f"{di}:ExitLock"))  # 0: released
        print("Locked:", await (await lock.get_child(f"{di}:Locked")).read_value())


if __name__ == "__main__":
    asyncio.run(lock(sys.argv[1]))
