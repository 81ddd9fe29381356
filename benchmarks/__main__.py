"""Start-up time and memory of `uacell serve`, side by side with a bare asyncua server.

The machines are shared and noisy, so absolute numbers mean little: each round starts both servers
one after the other and the report gives the ratio uacell / bare asyncua (median over the rounds).
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BARE = r"""
import asyncio, sys
from asyncua import Server
async def main():
    s = Server()
    await s.init()
    s.set_endpoint(f"opc.tcp://127.0.0.1:{sys.argv[1]}/")
    await s.start()
    print("uacell listening on", flush=True)
    await asyncio.sleep(3600)
asyncio.run(main())
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _measure(cmd: list[str]) -> tuple[float, int]:
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("uacell listening on"):
                break
        else:
            raise RuntimeError(f"{cmd[:3]} did not start")
        elapsed = time.perf_counter() - t0
        time.sleep(0.5)
        return elapsed, _rss_kib(proc.pid)
    finally:
        proc.terminate()
        proc.wait(30)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    startup, memory = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.rounds):
            bare_t, bare_m = _measure([sys.executable, "-c", BARE, str(_port())])
            cell_t, cell_m = _measure(
                [
                    sys.executable,
                    "-m",
                    "uacell",
                    "--log-level",
                    "ERROR",
                    "serve",
                    "--port",
                    str(_port()),
                    "--data-dir",
                    os.path.join(tmp, f"d{i}"),
                ]
            )
            startup.append(cell_t / bare_t)
            memory.append(cell_m / bare_m)
            print(
                f"round {i + 1}: start-up {cell_t:.2f}s vs {bare_t:.2f}s, "
                f"RSS {cell_m // 1024} MiB vs {bare_m // 1024} MiB"
            )
    print(f"start-up ratio uacell/bare asyncua (median): {statistics.median(startup):.2f}")
    print(f"memory ratio uacell/bare asyncua (median):   {statistics.median(memory):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
