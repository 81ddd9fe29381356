"""Profile the server side of one kind of call: ``python -m benchmarks.profile [--method SetMachSpeed]``.

Runs uacell (demo cell, acting times zero) in this process under cProfile while an asyncua client
calls the method (or cycle) ``--calls`` times, then prints the functions with the largest cumulative time below
the dispatcher. Client and server share the process: read the server's share (``dispatch``).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import logging
import pstats
import sys
import tempfile
from pathlib import Path

from asyncua import Client, ua

from benchmarks.cells import bench_cell
from benchmarks.harness import free_port

TC = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
# name -> the calls of one cycle: (object NodeId path, method, arguments)
CALLS = {
    "SetMachSpeed": [("Filler1", "SetMachSpeed", [ua.Variant(120.0, ua.VariantType.Float)])],
    "LoadCycle": [
        (TC, "LoadByName", [ua.Variant("pick_and_place", ua.VariantType.String)]),
        (TC, "UnloadProgram", []),
    ],
}


async def run(method: str, calls: int, cell: str) -> cProfile.Profile:
    from uacell.config import Config
    from uacell.server import UacellServer

    with tempfile.TemporaryDirectory() as tmp:
        config = Config()
        config.server.port = free_port()
        config.server.data_dir = Path(tmp)
        config.packml.acting_time = 0.0
        app = UacellServer(config, parts=bench_cell(cell))
        await app.setup()
        await app.start()
        ns = app.cell.instantiator.ns
        steps = [
            (ua.NodeId(path, ns), app.dispatcher.method_of(ua.NodeId(path, ns), name), args)
            for path, name, args in CALLS[method]
        ]
        profile = cProfile.Profile()
        try:
            async with Client(app.endpoint, timeout=30) as client:
                for i in range(20 + calls):
                    if i == 20:
                        profile.enable()
                    for obj, method_id, args in steps:
                        await client.get_node(obj).call_method(method_id, *args)
                profile.disable()
        finally:
            await app.stop()
        return profile


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.profile")
    parser.add_argument("--method", default="SetMachSpeed", choices=sorted(CALLS))
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--cell", default="demo")
    parser.add_argument("--limit", type=int, default=40)
    parser.add_argument("--filter", default="uacell|asyncua/server", help="regular expression on file names")
    parser.add_argument("--sort", default="cumulative", choices=("cumulative", "tottime"), help="order of the list")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    profile = asyncio.run(run(args.method, args.calls, args.cell))
    stats = pstats.Stats(profile, stream=sys.stdout)
    stats.sort_stats(args.sort).print_stats(args.filter, args.limit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
