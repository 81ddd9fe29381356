"""Upload a robot program into Controller1's Programs folder, as an engineer (OPC 10000-5 FileDirectoryType).

Usage: python upload_program.py ENDPOINT USER PASSWORD FILE
"""

import asyncio
import sys
from pathlib import Path

from asyncua import Client, ua

WRITE, ERASE_EXISTING = 2, 4  # Open's mode bits
CHUNK = 64 * 1024  # every Write request stays well below [limits] max_message_size (256 KiB)


async def upload(endpoint: str, user: str, password: str, path: Path) -> None:
    client = Client(endpoint)
    client.set_user(user)  # the password travels encrypted, even on the None endpoint
    client.set_password(password)
    async with client:
        cell = await client.get_namespace_index("urn:uacell:cell")
        programs = client.get_node(ua.NodeId("Robot1.Controllers.Controller1.Programs", cell))
        try:  # a file of that name: replace its content
            file = await programs.get_child(ua.QualifiedName(path.name, cell))  # (a string would read "." as a path)
        except ua.UaStatusCodeError:  # else create it (empty, not opened)
            file_id, _ = await programs.call_method("0:CreateFile", path.name, False)
            file = client.get_node(file_id)
        handle = await file.call_method("0:Open", ua.Variant(WRITE | ERASE_EXISTING, ua.VariantType.Byte))
        data = path.read_bytes()
        for start in range(0, len(data), CHUNK):
            await file.call_method("0:Write", ua.Variant(handle, ua.VariantType.UInt32), data[start : start + CHUNK])
        await file.call_method("0:Close", ua.Variant(handle, ua.VariantType.UInt32))  # the new content counts now
        print(f"uploaded {path.name}: {len(data)} bytes")


if __name__ == "__main__":
    endpoint, user, password, file = sys.argv[1:5]
    asyncio.run(upload(endpoint, user, password, Path(file)))
