"""Modbus register values: a typed value <-> 16-bit registers, with byte and word order.

Pure and transport-free. A register holds two bytes; ``byte_order`` is the order of the two bytes
inside each register, ``word_order`` the order of the registers of a multi-register value ("big" =
most significant first, the Modbus convention). Strings take a fixed number of registers, are
ASCII, and are padded with NUL on write and stripped of trailing NULs on read.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

Order = Literal["big", "little"]

# type name -> (struct format, number of registers); "string" is sized by the tag
_NUMERIC: dict[str, tuple[str, int]] = {
    "int16": ("h", 1),
    "uint16": ("H", 1),
    "int32": ("i", 2),
    "uint32": ("I", 2),
    "float32": ("f", 2),
    "int64": ("q", 4),
    "uint64": ("Q", 4),
    "float64": ("d", 4),
}
TYPES = (*_NUMERIC, "bool", "string")


class CodecError(ValueError):
    """A value or a register block that does not fit the declared type (message says which)."""


@dataclass(frozen=True)
class RegisterType:
    """How a tag's value is laid out in registers."""

    name: str
    byte_order: Order = "big"
    word_order: Order = "big"
    length: int = 0  # registers, only for "string"

    def __post_init__(self) -> None:
        if self.name not in TYPES:
            raise CodecError(f"type {self.name!r} is not one of {', '.join(TYPES)}")
        for what, order in (("byte_order", self.byte_order), ("word_order", self.word_order)):
            if order not in ("big", "little"):
                raise CodecError(f"{what} {order!r} is not 'big' or 'little'")
        if self.name == "string" and self.length < 1:
            raise CodecError("type 'string' needs a length of at least 1 register")
        if self.name != "string" and self.length:
            raise CodecError(f"type {self.name!r} takes no length")

    @property
    def count(self) -> int:
        """Number of registers (a bool in a register takes one)."""
        if self.name == "string":
            return self.length
        if self.name == "bool":
            return 1
        return _NUMERIC[self.name][1]

    def encode(self, value: object) -> list[int]:
        """Registers for ``value``; CodecError if it does not fit the type."""
        if self.name == "bool":
            if not isinstance(value, bool):
                raise CodecError(f"{value!r} is not a bool")
            return [1 if value else 0]
        if self.name == "string":
            if not isinstance(value, str):
                raise CodecError(f"{value!r} is not a string")
            try:
                raw = value.encode("ascii")
            except UnicodeEncodeError:
                raise CodecError(f"{value!r} is not ASCII") from None
            if len(raw) > 2 * self.length:
                raise CodecError(f"{value!r} is longer than {2 * self.length} characters")
            raw = raw.ljust(2 * self.length, b"\0")
        else:
            fmt = _NUMERIC[self.name][0]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise CodecError(f"{value!r} is not a number")
            if fmt != "f" and fmt != "d" and not isinstance(value, int):
                raise CodecError(f"{value!r} is not an integer")
            try:
                raw = struct.pack(">" + fmt, value)
            except (struct.error, OverflowError):
                raise CodecError(f"{value!r} is out of range for {self.name}") from None
        return self._to_registers(raw)

    def decode(self, registers: list[int]) -> bool | int | float | str:
        """The value held by ``registers``; CodecError on a wrong count or a non-16-bit word."""
        if len(registers) != self.count:
            raise CodecError(f"{self.name} takes {self.count} registers, got {len(registers)}")
        for r in registers:
            if not 0 <= r <= 0xFFFF:
                raise CodecError(f"register value {r} is not 16-bit")
        if self.name == "bool":
            return registers[0] != 0
        raw = self._from_registers(registers)
        if self.name == "string":
            try:
                return raw.rstrip(b"\0").decode("ascii")
            except UnicodeDecodeError:
                raise CodecError("registers do not hold ASCII text") from None
        (value,) = struct.unpack(">" + _NUMERIC[self.name][0], raw)
        return value  # type: ignore[no-any-return]

    def _to_registers(self, raw: bytes) -> list[int]:
        """Big-endian bytes (most significant word first) -> registers in the declared orders."""
        words = [raw[i : i + 2] for i in range(0, len(raw), 2)]
        if self.name != "string" and self.word_order == "little":
            words.reverse()
        if self.byte_order == "little":
            words = [w[::-1] for w in words]
        return [int.from_bytes(w, "big") for w in words]

    def _from_registers(self, registers: list[int]) -> bytes:
        words = [r.to_bytes(2, "big") for r in registers]
        if self.byte_order == "little":
            words = [w[::-1] for w in words]
        if self.name != "string" and self.word_order == "little":
            words.reverse()
        return b"".join(words)
