"""A Rockwell Logix controller holding ISA-TR88 PackTags as Logix tags: cpppo's EtherNet/IP Logix
simulator (``cpppo.server.enip``) with one unit's tags per name (``Capper.Command.CntrlCmd`` ...,
the names docs/equipment.md gives for ``logix-packtags``) and a scan-cycle program running each
unit's TR88 state machine, as the other example PLCs do.

    python -m uacell.gateway.examples.logix_plc --port 44818 --units Capper,Labeler --acting 0.1

cpppo cannot resolve an array index inside a dotted name, so each unit's arrays are top-level array
tags: ``<unit>_Parameter`` (REAL[5], for Command.Parameter[i].Value), ``<unit>_Alarm`` (DINT[4], for
Admin.Alarm[i].ID); a cell maps them (``map = { "Command.Parameter[0].Value" = "Capper_Parameter[0]" }``).
Test switches: ``<unit>_Refuse`` (requests are taken and ignored), ``<unit>_Frozen`` (no scan),
``<unit>_Fault`` (a rising edge aborts with StopReason 42), ``<unit>_Taken`` (REAL[5]: the parameters
the last Start took). A request is processed whole between two scans (one lock), as a controller's
communication does not land in the middle of a scan. Prints "listening" once it serves.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from typing import Any

from cpppo.server.enip import logix
from cpppo.server.enip import main as enip

from uacell.gateway.examples.packtags_plc import ABORTABLE, ACTING_NEXT, COMMANDS, MODE_CHANGE_IN, S

PARAMETERS, ALARMS = 5, 4
TAGS = {
    "Command.CntrlCmd": "DINT", "Command.CmdChangeRequest": "BOOL", "Command.UnitMode": "DINT",
    "Command.UnitModeChangeRequest": "BOOL", "Command.MachSpeed": "REAL", "Status.StateCurrent": "DINT",
    "Status.UnitModeCurrent": "DINT", "Status.CurMachSpeed": "REAL", "Status.MachSpeed": "REAL",
    "Admin.ProdProcessedCount": "DINT", "Admin.ProdDefectiveCount": "DINT", "Admin.StopReason.ID": "DINT",
}  # fmt: skip
LOCK = threading.Lock()


def definitions(unit: str) -> list[str]:
    """The cpppo tag definitions of one unit (``name=TYPE[count]``)."""
    out = [f"{unit}.{path}={kind}" for path, kind in TAGS.items()]
    out += [f"{unit}_Parameter=REAL[{PARAMETERS}]", f"{unit}_Alarm=DINT[{ALARMS}]", f"{unit}_Taken=REAL[{PARAMETERS}]"]
    return out + [f"{unit}_{switch}=BOOL" for switch in ("Refuse", "Frozen", "Fault")]


class Unit:
    def __init__(self, name: str, acting: float) -> None:
        self.name, self.acting = name, acting
        self.entered = time.monotonic()
        self.produced = 0.0
        self.last_scan = time.monotonic()
        self.last_fault = False

    def _attribute(self, tag: str) -> Any:
        return dict.__getitem__(enip.tags, tag).attribute  # a plain lookup: the name has dots

    def get(self, path: str, index: int = 0) -> Any:
        return self._attribute(f"{self.name}.{path}" if "." in path else f"{self.name}_{path}")[index]

    def set(self, path: str, value: Any, index: int = 0) -> None:
        self._attribute(f"{self.name}.{path}" if "." in path else f"{self.name}_{path}")[index] = value

    def enter(self, state: int, now: float) -> None:
        self.set("Status.StateCurrent", state)
        self.entered = now

    def initialise(self) -> None:
        self.set("Status.StateCurrent", S["Stopped"])
        self.set("Status.UnitModeCurrent", 1)
        self.set("Command.UnitMode", 1)
        self.set("Command.MachSpeed", 60.0)
        self.set("Status.MachSpeed", 60.0)

    def scan(self, now: float) -> None:
        if self.get("Frozen"):
            return
        refuse, fault = self.get("Refuse"), self.get("Fault")
        state = int(self.get("Status.StateCurrent"))
        if fault and not self.last_fault and state in ABORTABLE:
            self.set("Admin.StopReason.ID", 42)
            self.enter(state := S["Aborting"], now)
        self.last_fault = bool(fault)
        if self.get("Command.CmdChangeRequest"):
            self.set("Command.CmdChangeRequest", False)
            rule = COMMANDS.get(int(self.get("Command.CntrlCmd")))
            if not refuse and rule is not None and state in rule[0]:
                if rule[1] == S["Starting"]:
                    for i in range(PARAMETERS):
                        self.set("Taken", self.get("Parameter", i), i)
                self.enter(state := rule[1], now)
        if self.get("Command.UnitModeChangeRequest"):
            self.set("Command.UnitModeChangeRequest", False)
            if not refuse and state in MODE_CHANGE_IN:
                self.set("Status.UnitModeCurrent", self.get("Command.UnitMode"))
        speed = float(self.get("Command.MachSpeed"))
        if speed > 0:
            self.set("Status.MachSpeed", speed)
        if state in ACTING_NEXT and now - self.entered >= self.acting:
            self.enter(state := ACTING_NEXT[state], now)
        if state == S["Execute"]:
            self.set("Status.CurMachSpeed", speed)
            self.produced += speed / 60.0 * (now - self.last_scan)
            whole = int(self.produced)
            if whole:
                self.produced -= whole
                self.set("Admin.ProdProcessedCount", int(self.get("Admin.ProdProcessedCount")) + whole)
        else:
            self.set("Status.CurMachSpeed", 0.0)
        self.last_scan = now


def locked_process(addr: Any, data: Any, **kwds: Any) -> Any:
    """cpppo's Logix request processing, a whole request between two scans."""
    with LOCK:
        return logix.process(addr, data, **kwds)


def run(port: int, units: list[str], acting: float, period: float) -> None:
    program = [Unit(u, acting) for u in units]

    def scan() -> None:
        while not enip.tags:  # cpppo's main defines the tags first
            time.sleep(0.01)
        for unit in program:
            unit.initialise()
        time.sleep(0.2)  # the server binds its port
        print("listening", flush=True)
        while True:
            with LOCK:
                now = time.monotonic()
                for unit in program:
                    unit.scan(now)
            time.sleep(period)

    threading.Thread(target=scan, daemon=True).start()
    argv = ["-a", f"127.0.0.1:{port}", "--no-udp", *[d for u in units for d in definitions(u)]]
    enip.main(argv=argv, enip_process=locked_process)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--port", type=int, default=44818)
    parser.add_argument("--units", default="Capper", help="the units' tag names, comma separated")
    parser.add_argument("--acting", type=float, default=0.1, help="seconds an acting state takes")
    parser.add_argument("--scan", type=float, default=0.005, help="scan cycle in seconds")
    args = parser.parse_args()
    try:
        run(args.port, args.units.split(","), args.acting, args.scan)
    except KeyboardInterrupt:
        sys.exit(0)
