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
import contextlib
import os
import socket
import sys
import threading
import time
from typing import Any

from cpppo.server.enip import logix
from cpppo.server.enip import main as enip

from uacell.gateway.examples.scan import ScanProgram

PARAMETERS, ALARMS = 5, 4
TAGS = {
    "Command.CntrlCmd": "DINT", "Command.CmdChangeRequest": "BOOL", "Command.UnitMode": "DINT",
    "Command.UnitModeChangeRequest": "BOOL", "Command.MachSpeed": "REAL", "Status.StateCurrent": "DINT",
    "Status.UnitModeCurrent": "DINT", "Status.CurMachSpeed": "REAL", "Status.MachSpeed": "REAL",
    "Admin.ProdProcessedCount": "DINT", "Admin.ProdDefectiveCount": "DINT", "Admin.StopReason.ID": "DINT",
}  # fmt: skip
PATHS = {"Admin.StopReason": "Admin.StopReason.ID"}  # a map key -> its tag path, where they differ
LOCK = threading.Lock()


def definitions(unit: str) -> list[str]:
    """The cpppo tag definitions of one unit (``name=TYPE[count]``)."""
    out = [f"{unit}.{path}={kind}" for path, kind in TAGS.items()]
    out += [f"{unit}_Parameter=REAL[{PARAMETERS}]", f"{unit}_Alarm=DINT[{ALARMS}]", f"{unit}_Taken=REAL[{PARAMETERS}]"]
    return out + [f"{unit}_{switch}=BOOL" for switch in ("Refuse", "Frozen", "Fault")]


class Unit:
    """One unit's tags in cpppo's tag table (``scan.Memory``)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def _attribute(self, tag: str) -> Any:
        return dict.__getitem__(enip.tags, tag).attribute  # a plain lookup: the name has dots

    def get(self, tag: str) -> Any:
        return self._attribute(f"{self.name}.{PATHS.get(tag, tag)}")[0]

    def set(self, tag: str, value: Any) -> None:
        self._attribute(f"{self.name}.{PATHS.get(tag, tag)}")[0] = value

    def switches(self) -> tuple[bool, bool, bool]:
        refuse, frozen, fault = (bool(self._attribute(f"{self.name}_{s}")[0]) for s in ("Refuse", "Frozen", "Fault"))
        return refuse, frozen, fault

    def take_parameters(self) -> None:
        taken, given = self._attribute(f"{self.name}_Taken"), self._attribute(f"{self.name}_Parameter")
        for i in range(PARAMETERS):
            taken[i] = given[i]


def locked_process(addr: Any, data: Any, **kwds: Any) -> Any:
    """cpppo's Logix request processing, a whole request between two scans."""
    with LOCK:
        return logix.process(addr, data, **kwds)


def _serving(port: int) -> bool:
    """Does something accept connections on the port?"""
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
        return True
    return False


def run(port: int, units: list[str], acting: float, period: float) -> None:
    program = [ScanProgram(Unit(u), acting) for u in units]
    names = [d.split("=", 1)[0] for u in units for d in definitions(u)]

    def scan() -> None:
        # cpppo's main defines the tags one by one, then binds the port: both before "listening"
        while not all(dict.__contains__(enip.tags, name) for name in names) or not _serving(port):
            time.sleep(0.01)
        for unit in program:
            unit.initialise()
        print("listening", flush=True)
        while True:
            with LOCK:
                now = time.monotonic()
                for unit in program:
                    unit.scan(now)
            time.sleep(period)

    def scan_or_end() -> None:
        try:
            scan()
        except BaseException as exc:  # a PLC without its program is no PLC: end, so the parent sees it
            print(f"logix_plc: the scan stopped: {exc!r}", file=sys.stderr, flush=True)
            os._exit(1)

    threading.Thread(target=scan_or_end, daemon=True).start()
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
