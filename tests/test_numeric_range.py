"""NumericRange (OPC 10000-4 7.27), the IndexRange of Read and Write, as pure functions: the syntax the
standard allows and refuses (Bad_IndexRangeInvalid), and what a range selects of arrays, strings and
nested arrays (Bad_IndexRangeNoData where there is nothing)."""

from __future__ import annotations

import pytest
from asyncua import ua

from uacell.ua import numeric_range

SC = ua.StatusCodes


@pytest.mark.parametrize(
    ("text", "dimensions"),
    [("", ()), ("6", ((6, 6),)), ("5:7", ((5, 7),)), ("1:2,0:1", ((1, 2), (0, 1))), ("1,1", ((1, 1), (1, 1)))],
)
def test_numeric_range_parses(text: str, dimensions: tuple[numeric_range.Dimension, ...]) -> None:
    assert numeric_range.parse(text) == dimensions


@pytest.mark.parametrize("text", ["6,", "7:5", "5:5", " 1", "1 ", "-1", "01", "1:2:3", "a", "1;2", ","])
def test_numeric_range_refuses_its_syntax(text: str) -> None:
    with pytest.raises(numeric_range.RangeError) as refused:
        numeric_range.parse(text)
    assert refused.value.code == SC.BadIndexRangeInvalid


def test_numeric_range_selects() -> None:
    assert numeric_range.select([1, 2, 3], ((1, 5),)) == [2, 3]
    assert numeric_range.select("abcdef", ((2, 3),)) == "cd"
    assert numeric_range.select(b"\x00\x01\x02", ((1, 1),)) == b"\x01"
    assert numeric_range.select([[1, 2, 3], [4, 5, 6]], ((1, 1), (0, 1))) == [[4, 5]]
    for value, dims in ((5, ((0, 0),)), ([1], ((1, 1),)), ("ab", ((0, 0), (0, 0))), ([1, 2], ((0, 0), (0, 0)))):
        with pytest.raises(numeric_range.RangeError) as refused:
            numeric_range.select(value, dims)
        assert refused.value.code == SC.BadIndexRangeNoData
