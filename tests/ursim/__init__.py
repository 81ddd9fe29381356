"""A simulated Universal Robots controller for tests: the Dashboard Server text protocol, UR's Modbus
server register map and a control port, on one shared state. Written from UR's public documentation
only (see each module's docstring for its sources), never from uacell's code.

In process::

    sim = URSim(programs_dir)
    async with URSimServers(sim, dashboard_port, modbus_port) as servers:
        ...  # connect to 127.0.0.1:servers.dashboard_port; drive the cell with sim.emergency_stop() etc.

As a process: ``python -m tests.ursim --port P --programs-dir D --modbus-port M --control-port C``
(or ``python -m tests.ursim.dashboard ...``; see server.py and control.py).

The names below are imported on first use, so that running a submodule with ``-m`` does not import
it twice.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "NOT_REMOTE": "dashboard",
    "WELCOME": "dashboard",
    "Dashboard": "dashboard",
    "DashboardServer": "dashboard",
    "REGISTERS": "modbus",
    "URModbusServer": "modbus",
    "joint_angle": "modbus",
    "joint_registers": "modbus",
    "signed": "modbus",
    "ProgramState": "robot",
    "RobotMode": "robot",
    "SafetyStatus": "robot",
    "URSim": "robot",
    "Control": "control",
    "URSimServers": "server",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(name)
    return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
