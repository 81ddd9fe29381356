"""A Siemens S7 PLC keeping ISA-TR88 PackTags in a data block: python-snap7's own S7 server
(``snap7.server.Server``) holding DB 1 with the layout docs/equipment.md gives for ``s7-packtags``
(unit i from byte 200 * i; optimized block access off), and a small scan-cycle program running each
unit's TR88 state machine, as the Modbus example PLC does.

    python -m uacell.gateway.examples.s7_plc --port 10102 --units 2 --acting 0.1

Two things snap7's stock server does that a real S7 does not are corrected here, from the S7comm
"write variable" job as S7 CPUs answer it: a bit item (transport size BIT) changes that one bit,
not the whole byte; and every item of a multi-item job is written, in order, each answered with its
own return code (0xFF success, 0x0A no such data block, 0x05 out of range). Jobs are taken between
two scans (the data block's lock is held for a whole scan), as a CPU takes communication at its
cycle control point.

Test switches in each unit's own bytes: 160.0 refuse (requests are taken and ignored), 160.1 frozen
(no scan), 160.2 fault (a rising edge aborts with StopReason 42); from 164 the Command.Parameter
values the last Start took (REAL each). Prints "listening" once it serves.
"""

from __future__ import annotations

import argparse
import struct
import sys
import threading
import time
from typing import Any

from snap7.server import Server
from snap7.type import SrvArea

from uacell.gateway.examples.scan import ScanProgram

DB = 1
UNIT_BYTES = 200
# docs/equipment.md, "PackML units over PackTags on Siemens S7": tag -> (byte, S7 type)
LAYOUT = {
    "Status.StateCurrent": (0, "DINT"), "Status.UnitModeCurrent": (4, "DINT"), "Status.CurMachSpeed": (8, "REAL"),
    "Status.MachSpeed": (12, "REAL"), "Admin.ProdProcessedCount": (16, "DINT"),
    "Admin.ProdDefectiveCount": (20, "DINT"), "Admin.StopReason": (24, "DINT"), "Command.CntrlCmd": (28, "DINT"),
    "Command.UnitMode": (32, "DINT"), "Command.MachSpeed": (36, "REAL"),
}  # fmt: skip
BITS = {"Command.CmdChangeRequest": (40, 0), "Command.UnitModeChangeRequest": (40, 1)}  # (byte, bit): BOOL
PARAMETERS_AT, PARAMETERS = 74, 5
SWITCHES, TAKEN = 160, 164
FORMATS = {"DINT": ">i", "REAL": ">f"}


class PackTagsS7(Server):
    """snap7's server with S7 write jobs as a CPU answers them (module doc)."""

    def __init__(self, size: int) -> None:
        super().__init__(log=False)
        self.db = bytearray(size)
        self.register_area(SrvArea.DB, DB, self.db)
        self.lock = threading.Lock()  # held by a scan, and by a write job

    def _process_request(self, request_data: bytes, client_address: Any) -> bytes | None:
        if len(request_data) > 10 and request_data[1] == 0x01 and request_data[10] == 0x05:
            return self._write_job(request_data)
        with self.lock:
            return super()._process_request(request_data, client_address)

    def _write_job(self, pdu: bytes) -> bytes:
        reference, param_len = struct.unpack(">HH", pdu[4:8])
        params, data = pdu[10 : 10 + param_len], pdu[10 + param_len :]
        count = params[1]
        codes = []
        at = 0
        with self.lock:
            for i in range(count):
                spec = params[2 + 12 * i : 14 + 12 * i]
                transport, _n, db, area = struct.unpack(">BHHB", spec[3:9])
                address = int.from_bytes(spec[9:12], "big")
                _ret, size_kind, length = struct.unpack(">BBH", data[at : at + 4])
                size = length // 8 if size_kind in (0x04, 0x05) else length  # bits, or bytes (BIT: a byte each)
                value = data[at + 4 : at + 4 + size]
                at += 4 + size + (size % 2 if i < count - 1 else 0)
                codes.append(self._write_item(db, area, transport, address, value))
        header = struct.pack(">BBHHHHBB", 0x32, 0x03, 0x0000, reference, 2, count, 0, 0)
        return header + bytes([0x05, count]) + bytes(codes)

    def _write_item(self, db: int, area: int, transport: int, address: int, value: bytes) -> int:
        if area != 0x84 or db != DB:
            return 0x0A  # object does not exist
        byte, bit = address >> 3, address & 7
        if byte + max(1, len(value)) > len(self.db) or not value:
            return 0x05  # address out of range
        if transport == 0x01:  # one bit: that bit only
            self.db[byte] = self.db[byte] | (1 << bit) if value[0] & 1 else self.db[byte] & ~(1 << bit)
        else:
            self.db[byte : byte + len(value)] = value
        return 0xFF


class Unit:
    """One unit's PackTags in the data block (``scan.Memory``), from byte ``base``."""

    def __init__(self, plc: PackTagsS7, base: int) -> None:
        self.plc, self.base = plc, base

    def get(self, tag: str) -> Any:
        if tag in BITS:
            byte, bit = BITS[tag]
            return bool(self.plc.db[self.base + byte] >> bit & 1)
        offset, kind = LAYOUT[tag]
        (value,) = struct.unpack_from(FORMATS[kind], self.plc.db, self.base + offset)
        return value

    def set(self, tag: str, value: Any) -> None:
        if tag in BITS:
            byte, bit = BITS[tag]
            at = self.base + byte
            self.plc.db[at] = self.plc.db[at] | (1 << bit) if value else self.plc.db[at] & ~(1 << bit)
            return
        offset, kind = LAYOUT[tag]
        struct.pack_into(FORMATS[kind], self.plc.db, self.base + offset, value)

    def switches(self) -> tuple[bool, bool, bool]:
        refuse, frozen, fault = (bool(self.plc.db[self.base + SWITCHES] >> b & 1) for b in range(3))
        return refuse, frozen, fault

    def take_parameters(self) -> None:
        at, to = self.base + PARAMETERS_AT, self.base + TAKEN
        self.plc.db[to : to + 4 * PARAMETERS] = self.plc.db[at : at + 4 * PARAMETERS]


def main(port: int, units: int, acting: float, period: float) -> None:
    plc = PackTagsS7(UNIT_BYTES * units)
    program = [ScanProgram(Unit(plc, UNIT_BYTES * i), acting) for i in range(units)]
    for unit in program:
        unit.initialise()
    plc.start_to("127.0.0.1", port)
    print("listening", flush=True)
    try:
        while True:
            with plc.lock:
                now = time.monotonic()
                for unit in program:
                    unit.scan(now)
            time.sleep(period)
    finally:
        plc.stop()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--port", type=int, default=10102)
    parser.add_argument("--units", type=int, default=1, help="units, unit i from byte 200 * i of DB 1")
    parser.add_argument("--acting", type=float, default=0.1, help="seconds an acting state takes")
    parser.add_argument("--scan", type=float, default=0.005, help="scan cycle in seconds")
    args = parser.parse_args()
    try:
        main(args.port, args.units, args.acting, args.scan)
    except KeyboardInterrupt:
        sys.exit(0)
