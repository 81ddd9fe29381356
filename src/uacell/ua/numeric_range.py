"""NumericRange, the IndexRange of Read, Write and monitored items (OPC 10000-4 7.27).

A range is one index ("6") or a pair of indexes of which the first is the lower ("5:7"; "7:5" and "5:5"
are invalid), one per dimension, separated by commas ("1:2,0:1"); nothing else, no white space. Strings
and ByteStrings count as arrays of characters and bytes: a dimension after an array's last one selects
a substring of each element.

Reading: a lower bound beyond the value is Bad_IndexRangeNoData, an upper bound beyond it gives what
there is. Bad_IndexRangeInvalid is for the syntax alone; any other request a value cannot answer (a
range on a scalar number, more dimensions than the value has) is Bad_IndexRangeNoData.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

from asyncua import ua

Dimension = tuple[int, int]  # (first index, last index), both included

_DIMENSION = re.compile(r"(0|[1-9][0-9]*)(?::(0|[1-9][0-9]*))?")


class RangeError(Exception):
    """A range that cannot be applied; ``code`` is the status code to answer."""

    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCode(code).name)
        self.code = code


def parse(text: str | None) -> tuple[Dimension, ...]:
    """The dimensions of ``text``; () for a null or empty range. RangeError(Bad_IndexRangeInvalid) for
    anything else that is not a NumericRange."""
    if not text:
        return ()
    dimensions: list[Dimension] = []
    for part in text.split(","):
        match = _DIMENSION.fullmatch(part)
        if match is None:
            raise RangeError(ua.StatusCodes.BadIndexRangeInvalid)
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        if match.group(2) is not None and last <= first:
            raise RangeError(ua.StatusCodes.BadIndexRangeInvalid)
        dimensions.append((first, last))
    return tuple(dimensions)


def select(value: Any, dimensions: tuple[Dimension, ...]) -> Any:
    """The part of ``value`` (a list, possibly nested, a str or bytes) the dimensions name.
    RangeError(Bad_IndexRangeNoData) when the value has none of it."""
    if not dimensions:
        return value
    (first, last), rest = dimensions[0], dimensions[1:]
    if isinstance(value, (str, bytes)):
        if rest:
            raise RangeError(ua.StatusCodes.BadIndexRangeNoData)
    elif not isinstance(value, list):
        raise RangeError(ua.StatusCodes.BadIndexRangeNoData)
    if first >= len(value):
        raise RangeError(ua.StatusCodes.BadIndexRangeNoData)
    part = value[first : last + 1]
    if isinstance(part, (str, bytes)):
        return part
    return [select(element, rest) for element in part]


def cut(read: ua.DataValue, text: str) -> ua.DataValue:
    """The part of a read or monitored value a client's IndexRange names: a new DataValue (the one given
    may be the address space's own), with the value's status and timestamps; the range's status code
    and no value when it names nothing. A value whose status is bad is left as it is."""
    if read.StatusCode is not None and not read.StatusCode.is_good():
        return read
    try:
        variant = read.Value
        if variant is None or variant.Value is None:
            raise RangeError(ua.StatusCodes.BadIndexRangeNoData)
        part = ua.Variant(select(variant.Value, parse(text)), variant.VariantType)
    except RangeError as refused:
        return dataclasses.replace(read, Value=None, StatusCode=ua.StatusCode(refused.code))
    return dataclasses.replace(read, Value=part)
