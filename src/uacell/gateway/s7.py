"""Siemens S7 data block addresses and values, and the S7 write job, as pure functions.

An address is absolute, as STEP 7 / TIA Portal shows it for a data block with optimized block access
off: ``DB1.DBD0`` (a double word at byte 0 of DB 1: a DINT or a REAL), ``DB1.DBW4`` (a word: an
INT), ``DB1.DBB6`` (a byte), ``DB1.DBX40.1`` (bit 1 of byte 40: a BOOL). Values are big-endian, as
an S7 keeps them. ``write_job`` builds one S7 "write variable" job (function 0x05, S7comm) with one
item per block of neighbouring bytes and one per bit: a real S7 writes each item as given (a bit item
changes that bit only) and answers one return code per item; ``write_results`` reads them.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

# S7 type -> (size in bytes, struct format); BOOL is one bit
TYPES: dict[str, tuple[int, str]] = {
    "BOOL": (1, ""),
    "BYTE": (1, ">B"),
    "INT": (2, ">h"),
    "DINT": (4, ">i"),
    "REAL": (4, ">f"),
}
_SIZE_LETTER = {"X": ("BOOL",), "B": ("BYTE",), "W": ("INT",), "D": ("DINT", "REAL")}
_ADDRESS = re.compile(r"^DB(\d+)\.DB([XBWD])(\d+)(?:\.([0-7]))?$")
AREA_DB = 0x84
# S7 return codes of a data item (S7comm)
RETURN_CODES = {
    0x01: "hardware fault",
    0x03: "object access not allowed",
    0x05: "address out of range",
    0x06: "data type not supported",
    0x07: "data type inconsistent",
    0x0A: "object does not exist",
}


class S7AddressError(ValueError):
    """An address or a value that does not fit (the message says which)."""


@dataclass(frozen=True, order=True)
class S7Address:
    db: int
    byte: int
    bit: int  # 0..7 for a BOOL, else 0
    kind: str  # a key of TYPES

    @property
    def size(self) -> int:
        return TYPES[self.kind][0]

    def __str__(self) -> str:
        if self.kind == "BOOL":
            return f"DB{self.db}.DBX{self.byte}.{self.bit}"
        letter = {"BYTE": "B", "INT": "W", "DINT": "D", "REAL": "D"}[self.kind]
        text = f"DB{self.db}.DB{letter}{self.byte}"
        return f"{text} {self.kind}" if letter == "D" else text

    @classmethod
    def parse(cls, text: str, kind: str = "") -> S7Address:
        """``DB1.DBD0 REAL``, ``DB1.DBD0`` with ``kind``, ``DB1.DBX40.1``; S7AddressError if not one."""
        address, _, given = text.strip().partition(" ")
        m = _ADDRESS.match(address.strip().upper())
        if m is None:
            raise S7AddressError(f"{text!r} is not an absolute data block address (DB1.DBD0, DB1.DBW4, DB1.DBX40.1)")
        db, letter, byte, bit = int(m[1]), m[2], int(m[3]), m[4]
        kinds = _SIZE_LETTER[letter]
        chosen = given.strip().upper() or kind or kinds[0]
        if chosen not in kinds:
            raise S7AddressError(f"{text!r}: a DB{letter} holds {' or '.join(kinds)}, not {chosen}")
        if (bit is not None) != (letter == "X"):
            raise S7AddressError(f"{text!r}: a bit address is DBX<byte>.<bit>, other sizes have no bit")
        if not 1 <= db <= 65535 or byte > 65535:
            raise S7AddressError(f"{text!r}: DB 1..65535, byte 0..65535")
        return cls(db, byte, int(bit or 0), chosen)

    def decode(self, block: bytes | bytearray, start: int) -> bool | int | float:
        """The value in ``block``, a read of this address's data block from byte ``start``."""
        at = self.byte - start
        if self.kind == "BOOL":
            return bool(block[at] >> self.bit & 1)
        (value,) = struct.unpack(TYPES[self.kind][1], bytes(block[at : at + self.size]))
        return value  # type: ignore[no-any-return]

    def encode(self, value: object) -> bytes:
        """The bytes of ``value`` (a BOOL: one byte, 0 or 1, for a bit item)."""
        if self.kind == "BOOL":
            if not isinstance(value, bool):
                raise S7AddressError(f"{self}: {value!r} is not a bool")
            return b"\x01" if value else b"\x00"
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise S7AddressError(f"{self}: {value!r} is not a number")
        if self.kind != "REAL" and not isinstance(value, int):
            raise S7AddressError(f"{self}: {value!r} is not an integer")
        try:
            return struct.pack(TYPES[self.kind][1], value)
        except (struct.error, OverflowError):
            raise S7AddressError(f"{self}: {value!r} is out of range for {self.kind}") from None


@dataclass(frozen=True)
class ByteSpan:
    """Bytes of one data block read in one request."""

    db: int
    start: int
    count: int


def byte_spans(addresses: list[S7Address], gap: int = 200, most: int = 200) -> list[ByteSpan]:
    """The fewest reads that cover every address: addresses of one data block closer than ``gap``
    bytes together, no read longer than ``most`` bytes (what one S7 PDU of 240 bytes carries). The
    bytes between are read too: a unit's tags (200 bytes) come in one read, from one scan, so a
    cleared request and the state it led to are seen together."""
    out: list[ByteSpan] = []
    for db in sorted({a.db for a in addresses}):
        current: ByteSpan | None = None
        for a in sorted(x for x in addresses if x.db == db):
            end = a.byte + a.size
            if current is not None and a.byte - (current.start + current.count) <= gap and end - current.start <= most:
                current = ByteSpan(db, current.start, max(current.start + current.count, end) - current.start)
                out[-1] = current
                continue
            current = ByteSpan(db, a.byte, a.size)
            out.append(current)
    return out


@dataclass(frozen=True)
class WriteItem:
    """One item of a write job: ``data`` from ``byte`` of data block ``db``, or one bit (``bit`` set)."""

    db: int
    byte: int
    data: bytes
    bit: int | None = None


def write_items(writes: list[tuple[S7Address, object]]) -> list[WriteItem]:
    """The writes as items, in order: neighbouring bytes of one data block in one item, each bit alone."""
    items: list[WriteItem] = []
    for address, value in writes:
        data = address.encode(value)
        if address.kind == "BOOL":
            items.append(WriteItem(address.db, address.byte, data, address.bit))
            continue
        last = items[-1] if items else None
        if last and last.bit is None and last.db == address.db and last.byte + len(last.data) == address.byte:
            items[-1] = WriteItem(last.db, last.byte, last.data + data)
        else:
            items.append(WriteItem(address.db, address.byte, data))
    return items


def write_job(reference: int, items: list[WriteItem]) -> bytes:
    """The S7 PDU of one "write variable" job (S7comm: header, parameter, data), every item in it."""
    parameters = struct.pack(">BB", 0x05, len(items))
    data = b""
    for i, item in enumerate(items):
        if item.bit is not None:  # transport size BIT, one element; its address in bits
            parameters += struct.pack(">BBBBHH", 0x12, 0x0A, 0x10, 0x01, 1, item.db)
            parameters += struct.pack(">B", AREA_DB) + ((item.byte << 3) | item.bit).to_bytes(3, "big")
            data += struct.pack(">BBH", 0x00, 0x03, 1) + item.data
        else:  # transport size BYTE, len(data) elements; the data length in bits
            parameters += struct.pack(">BBBBHH", 0x12, 0x0A, 0x10, 0x02, len(item.data), item.db)
            parameters += struct.pack(">B", AREA_DB) + (item.byte << 3).to_bytes(3, "big")
            data += struct.pack(">BBH", 0x00, 0x04, len(item.data) * 8) + item.data
        if len(data) % 2 and i < len(items) - 1:
            data += b"\x00"  # each item's data but the last is padded to an even length
    header = struct.pack(">BBHHHH", 0x32, 0x01, 0x0000, reference & 0xFFFF, len(parameters), len(data))
    return header + parameters + data


def write_results(raw: bytes, count: int) -> list[str]:
    """What each item of a write job's answer says: "" for success (0xFF), else the reason."""
    codes = list(raw[:count])
    if len(codes) != count:
        raise S7AddressError(f"the answer has {len(codes)} return codes for {count} items")
    return ["" if c == 0xFF else f"{RETURN_CODES.get(c, 'refused')} (0x{c:02x})" for c in codes]
