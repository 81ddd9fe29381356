"""Pure pieces of the gateway (issue 21): Modbus register codec and the PackTags default map."""

from __future__ import annotations

import pytest

from uacell.gateway.codec import CodecError, RegisterType
from uacell.gateway.packtags import PackTagsMapError, resolve


@pytest.mark.parametrize(
    ("rtype", "value", "registers"),
    [
        (RegisterType("int16"), -2, [0xFFFE]),
        (RegisterType("uint16"), 513, [0x0201]),
        (RegisterType("uint16", byte_order="little"), 513, [0x0102]),
        (RegisterType("uint32"), 0x01020304, [0x0102, 0x0304]),
        (RegisterType("uint32", word_order="little"), 0x01020304, [0x0304, 0x0102]),
        (RegisterType("uint32", byte_order="little", word_order="little"), 0x01020304, [0x0403, 0x0201]),
        (RegisterType("float32"), 1.5, [0x3FC0, 0x0000]),
        (RegisterType("float32", word_order="little"), 1.5, [0x0000, 0x3FC0]),
        (RegisterType("int64"), -1, [0xFFFF] * 4),
        (RegisterType("float64"), 2.0, [0x4000, 0, 0, 0]),
        (RegisterType("bool"), True, [1]),
        (RegisterType("string", length=3), "abc", [0x6162, 0x6300, 0x0000]),
        (RegisterType("string", length=2, byte_order="little"), "abc", [0x6261, 0x0063]),
    ],
)
def test_round_trip(rtype: RegisterType, value: object, registers: list[int]) -> None:
    assert rtype.encode(value) == registers
    assert rtype.decode(registers) == value
    assert rtype.count == len(registers)


@pytest.mark.parametrize(
    ("rtype", "value", "message"),
    [
        (RegisterType("int16"), 40000, "out of range for int16"),
        (RegisterType("uint16"), -1, "out of range for uint16"),
        (RegisterType("int32"), 1.5, "not an integer"),
        (RegisterType("int32"), True, "not a number"),
        (RegisterType("bool"), 1, "not a bool"),
        (RegisterType("string", length=1), "abc", "longer than 2 characters"),
        (RegisterType("string", length=2), "é", "not ASCII"),
    ],
)
def test_encode_refuses(rtype: RegisterType, value: object, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        rtype.encode(value)


def test_decode_refuses_wrong_count_and_wide_words() -> None:
    with pytest.raises(CodecError, match="takes 2 registers, got 1"):
        RegisterType("float32").decode([0])
    with pytest.raises(CodecError, match="not 16-bit"):
        RegisterType("uint16").decode([0x10000])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"name": "int8"}, "type 'int8' is not one of"),
        ({"name": "int32", "word_order": "middle"}, "word_order 'middle'"),
        ({"name": "string"}, "needs a length"),
        ({"name": "int16", "length": 2}, "takes no length"),
    ],
)
def test_bad_declaration(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(CodecError, match=message):
        RegisterType(**kwargs)  # type: ignore[arg-type]


def test_packtags_defaults_under_prefix_and_overrides() -> None:
    tags = resolve("Capper", "ns=3;s=Capper.PackTags", {"Status.StateCurrent": "ns=3;i=77"}, parameters=2, alarms=1)
    assert tags["Command.CntrlCmd"].address == "ns=3;s=Capper.PackTags.Command.CntrlCmd"
    assert tags["Command.CntrlCmd"].type_name == "Int32"
    assert tags["Status.StateCurrent"].address == "ns=3;i=77"
    assert tags["Command.Parameter[1].Value"].address == "ns=3;s=Capper.PackTags.Command.Parameter[1].Value"
    assert "Command.Parameter[2].Value" not in tags
    assert tags["Admin.Alarm[0].ID"].address == "ns=3;s=Capper.PackTags.Admin.Alarm[0].ID"


def test_packtags_under_a_browse_path_prefix() -> None:
    tags = resolve("Capper", "/3:Line1/3:Capper/3:PackTags/", parameters=1)
    assert tags["Command.CntrlCmd"].address == "/3:Line1/3:Capper/3:PackTags/3:Command/3:CntrlCmd"
    assert tags["Command.Parameter[0].Value"].address == "/3:Line1/3:Capper/3:PackTags/3:Command/3:Parameter[0]/3:Value"
    assert tags["Admin.StopReason"].address == "/3:Line1/3:Capper/3:PackTags/3:Admin/3:StopReason/3:ID"
    with pytest.raises(PackTagsMapError, match=r"^Capper: prefix: '/Capper/PackTags': each browse name is"):
        resolve("Capper", "/Capper/PackTags")


def test_packtags_map_errors_name_part_and_tag() -> None:
    with pytest.raises(PackTagsMapError, match=r"^Capper: Status\.Bogus: not a PackTags tag of the map$"):
        resolve("Capper", "ns=3;s=P", {"Status.Bogus": "ns=3;i=1"})
    with pytest.raises(PackTagsMapError, match=r"^Capper: Command\.CntrlCmd: empty NodeId$"):
        resolve("Capper", "ns=3;s=P", {"Command.CntrlCmd": " "})
    with pytest.raises(PackTagsMapError, match=r"^Capper: prefix: empty"):
        resolve("Capper", "")
    with pytest.raises(PackTagsMapError, match=r"^Capper: Command\.CmdChangeRequest: no prefix and no override$"):
        resolve("Capper", "", {"Command.CntrlCmd": "ns=3;i=1"})
