"""Equipment simulators to try the gateway with no PLC (run them as ``python -m``)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any


async def run_plc(server: Any, scan: Callable[[float], Awaitable[None]], period: float) -> None:
    """Serve ``server`` (a pymodbus server) and call ``scan(now)`` every ``period`` seconds; prints
    "listening" once clients can connect. The program and the server live and die together: a
    failing scan ends the process."""

    async def program() -> None:
        while True:
            await scan(time.monotonic())
            await asyncio.sleep(period)

    serve = asyncio.create_task(server.serve_forever())
    cycle = asyncio.create_task(program())
    while not server.transport:  # not listening yet
        if serve.done():
            serve.result()
        await asyncio.sleep(0.01)
    print("listening", flush=True)
    done, pending = await asyncio.wait({serve, cycle}, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
    for task in done:
        task.result()
