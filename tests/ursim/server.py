"""One simulated UR controller on loopback ports: the Dashboard Server, the Modbus server and the
control port, all on one URSim. In process (``async with URSimServers(...)``) or as its own process::

    python -m tests.ursim.dashboard --port P --programs-dir D [--modbus-port M] [--control-port C]
        [--local] [--program-seconds S] [--unlock-delay S] [--boot-seconds S]

(from the repository root; ``PYTHONPATH=tests python -m ursim.dashboard ...`` works too). The process
prints one line ``ursim ready dashboard=P modbus=M control=C`` once every port listens, and exits on
SIGTERM/SIGINT or after the Dashboard command ``shutdown``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from pathlib import Path
from types import TracebackType

from .control import Control, ControlServer
from .dashboard import DashboardServer
from .modbus import URModbusServer
from .robot import URSim


class URSimServers:
    """The controller's ports around one URSim. ``kill``/``restart`` take the controller away and back
    on the same ports (the control port stays up)."""

    def __init__(
        self, sim: URSim, dashboard_port: int = 0, modbus_port: int | None = None, control_port: int | None = None
    ) -> None:
        self.sim = sim
        self.dashboard = DashboardServer(sim, dashboard_port)
        self.modbus = URModbusServer(sim, modbus_port) if modbus_port is not None else None
        self.control = (
            ControlServer(Control(sim, self.kill, self.restart), control_port) if control_port is not None else None
        )
        self.shutdown_requested = asyncio.Event()
        self.dashboard.dashboard.on_shutdown = self._on_shutdown

    @property
    def dashboard_port(self) -> int:
        return self.dashboard.port

    @property
    def received(self) -> list[str]:
        """Every Dashboard command line received so far."""
        return self.dashboard.dashboard.received

    async def start(self) -> None:
        """Listen on every port; when one cannot be had, close those already open and raise."""
        try:
            await self.dashboard.start()
            if self.modbus is not None:
                await self.modbus.start()
            if self.control is not None:
                await self.control.start()
        except BaseException:
            await self.stop()
            raise

    async def stop(self) -> None:
        if self.control is not None:
            await self.control.stop()
        await self.kill()

    async def kill(self) -> None:
        """The controller is gone: its ports close and open connections drop, unanswered."""
        await self.dashboard.stop()
        if self.modbus is not None:
            await self.modbus.stop()

    async def restart(self) -> None:
        """The controller boots again (power off, no program loaded) on the same ports."""
        await self.kill()
        self.sim.reboot()
        await self.dashboard.start()
        if self.modbus is not None:
            await self.modbus.start()

    def _on_shutdown(self) -> None:
        self.shutdown_requested.set()
        asyncio.get_running_loop().call_soon(lambda: asyncio.ensure_future(self.kill()))

    async def __aenter__(self) -> URSimServers:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="ursim", description="A simulated UR controller on 127.0.0.1")
    parser.add_argument("--port", type=int, required=True, help="Dashboard Server port (29999 on a robot)")
    parser.add_argument("--programs-dir", type=Path, required=True, help="the controller's programs (*.urp)")
    parser.add_argument("--modbus-port", type=int, help="Modbus server port (502 on a robot)")
    parser.add_argument("--control-port", type=int, help="the test control port (see control.py)")
    parser.add_argument("--local", action="store_true", help="start in Local control (default: Remote)")
    parser.add_argument("--program-seconds", type=float, help="a program ends by itself after this long")
    parser.add_argument("--unlock-delay", type=float, default=5.0, help="UR's wait before unlock (s)")
    parser.add_argument("--boot-seconds", type=float, default=0.05, help="POWER_ON to IDLE (s)")
    return parser.parse_args(argv)


async def serve(args: argparse.Namespace) -> None:
    sim = URSim(
        args.programs_dir,
        program_seconds=args.program_seconds,
        unlock_delay=args.unlock_delay,
        boot_seconds=args.boot_seconds,
    )
    sim.remote_control = not args.local
    servers = URSimServers(sim, args.port, args.modbus_port, args.control_port)
    await servers.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    modbus = servers.modbus.port if servers.modbus else "-"
    control = servers.control.port if servers.control else "-"
    print(f"ursim ready dashboard={servers.dashboard_port} modbus={modbus} control={control}", flush=True)
    waiters = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(servers.shutdown_requested.wait())]
    await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
    for waiter in waiters:
        waiter.cancel()
    await servers.stop()


def main(argv: list[str] | None = None) -> None:
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(parse(argv)))
    sys.exit(0)
