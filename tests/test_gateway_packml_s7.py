"""PackML units whose state machine runs in a Siemens S7 PLC, served by uacell from the cell file
alone (the s7-packtags driver): python-snap7's own S7 server holds the PackTags in data block 1 and
runs a TR88 scan-cycle program (uacell.gateway.examples.s7_plc, which answers S7 write jobs as a CPU
does: bit items change one bit, every item of a job is written) on a free port; an asyncua client
(and node-opcua once) drives uacell, which drives the PLC.

The scenarios every polled PackTags driver passes (a full cycle, a refused and a frozen command, a
fault, the PLC killed and back, node-opcua's cycle) are in test_gateway_packml_acceptance.py; here
is what only this transport has."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client
from conftest import fast_config, serving
from gateway_plcs import S7PLC, serving_cell
from gateway_plcs import s7_cell as shipped_cell
from helpers import (
    call_path,
    config_check_connect,
    free_port,
    until,
)

from uacell.config import load_cell
from uacell.gateway.packml_s7 import S7Connection, resolve_s7, where
from uacell.gateway.s7 import ByteSpan, S7Address, WriteItem, byte_spans, write_items, write_job, write_results
from uacell.server import UacellServer

F, L = "Capper", "Labeler"  # the shipped cell's units: bytes from 0 and from 200 of DB 1


def machines(unit: str) -> tuple[str, str, str]:
    base = f"{unit}.BaseStateMachine"
    return base, f"{base}.MachineState", f"{base}.MachineState.ExecuteState"


@pytest.fixture
async def plc() -> AsyncIterator[S7PLC]:
    p = S7PLC()
    p.start()
    try:
        await p.open()
        yield p
    finally:
        await p.close()
        p.kill()


@pytest.fixture
async def served(tmp_path: Path, plc: S7PLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    async with serving_cell(tmp_path, shipped_cell(plc)) as s:  # the shipped example, pointed at the PLC
        yield s


# -- addresses, the layout and the write job, pure ----------------------------------------------------


def test_the_default_layout_from_a_start_and_overrides() -> None:
    tags = resolve_s7("Capper", 10, start=200, parameters=2, alarms=1)
    assert tags["Status.StateCurrent"].address == "DB10.DBD200 DINT"
    assert tags["Status.MachSpeed"].address == "DB10.DBD212 REAL"
    assert tags["Command.CmdChangeRequest"].address == "DB10.DBX240.0"
    assert tags["Command.UnitModeChangeRequest"].address == "DB10.DBX240.1"
    assert tags["Admin.Alarm[0].ID"].address == "DB10.DBD242 DINT"
    assert tags["Command.Parameter[1].Value"].address == "DB10.DBD278 REAL"
    assert "Command.Parameter[2].Value" not in tags
    moved = resolve_s7("Capper", 1, overrides={"Status.StateCurrent": "DB7.DBW20", "Status.MachSpeed": "DB7.DBD4"})
    assert (moved["Status.StateCurrent"].address, moved["Status.MachSpeed"].address) == ("DB7.DBW20", "DB7.DBD4 REAL")
    held = resolve_s7("Capper", 1, overrides={"Status.MachSpeed": "db7.dbd4 dint"})["Status.MachSpeed"]
    assert S7Address.parse(held.address) == S7Address(7, 4, 0, "DINT")


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"map": {"Status.StateCurrent": "DB1.DBX0.0"}}, "Status.StateCurrent: a BOOL cannot hold the Int32"),
        ({"map": {"Command.CmdChangeRequest": "DB1.DBD0"}}, "a DBD holds DINT or REAL, not BOOL"),
        ({"map": {"Status.Nope": "DB1.DBD0"}}, "Capper: map: Status.Nope: not a PackTags tag of the map"),
        ({"map": {"Status.StateCurrent": "MD20"}}, "'MD20' is not an absolute data block address"),
        ({"map": {"Status.StateCurrent": "DB1.DBX4"}}, "a bit address is DBX<byte>.<bit>"),
        ({"map": {"Status.StateCurrent": 7}}, 'needs an address such as "DB7.DBD20"'),
        ({"parameters": 21}, "Capper: parameters: a whole number from 0 to 20"),
        ({"slot": 40}, "Capper: slot: a whole number from 0 to 31"),
        ({"db": 0}, "Capper: db: a whole number from 1 to 65535"),
        ({"interval": 0}, "Capper: interval"),
        ({"bogus": 1}, "the s7-packtags driver has no setting 'bogus'"),
        ({"host": ""}, "Capper: host"),
    ],
)  # fmt: skip
def test_settings_that_cannot_work_are_one_line(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        where("Capper", {"host": "plc"} | settings)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_nearby_bytes_are_read_in_one_request() -> None:
    tags = [S7Address.parse(t.address) for t in resolve_s7("U", 1, 0, alarms=2).values()]
    # one read: a unit's state and its change request come from the same scan
    assert byte_spans(tags) == [ByteSpan(1, 0, 94)]
    far = [S7Address(1, 0, 0, "DINT"), S7Address(1, 400, 0, "DINT"), S7Address(2, 0, 0, "BOOL")]
    assert byte_spans(far) == [ByteSpan(1, 0, 4), ByteSpan(1, 400, 4), ByteSpan(2, 0, 1)]
    wide = [S7Address(1, b, 0, "DINT") for b in range(0, 400, 10)]
    assert all(s.count <= 200 for s in byte_spans(wide)) and len(byte_spans(wide)) == 2


def test_a_command_is_one_write_job_bits_as_bit_items() -> None:
    """The S7comm "write variable" job, byte by byte: the parameters and the command in one byte item
    (neighbours), the change request as a bit item (transport size BIT, its address in bits)."""
    writes: list[tuple[S7Address, object]] = [
        (S7Address(1, 74, 0, "REAL"), 1.5),
        (S7Address(1, 78, 0, "REAL"), 2.0),
        (S7Address(1, 28, 0, "DINT"), 2),
        (S7Address(1, 40, 0, "BOOL"), True),
    ]
    items = write_items(writes)
    assert items == [
        WriteItem(1, 74, struct.pack(">ff", 1.5, 2.0)),
        WriteItem(1, 28, struct.pack(">i", 2)),
        WriteItem(1, 40, b"\x01", bit=0),
    ]
    pdu = write_job(7, items)
    header, params = pdu[:10], pdu[10 : 10 + 2 + 3 * 12]
    assert struct.unpack(">BBHHHH", header) == (0x32, 0x01, 0, 7, 2 + 36, 4 + 8 + 4 + 4 + 4 + 1)
    assert params[:2] == b"\x05\x03"
    assert params[2:14] == bytes([0x12, 0x0A, 0x10, 0x02, 0, 8, 0, 1, 0x84]) + (74 * 8).to_bytes(3, "big")
    assert params[26:38] == bytes([0x12, 0x0A, 0x10, 0x01, 0, 1, 0, 1, 0x84]) + (40 * 8 + 0).to_bytes(3, "big")
    data = pdu[10 + 38 :]
    assert data[:4] == bytes([0, 0x04, 0, 64]) and data[4:12] == struct.pack(">ff", 1.5, 2.0)
    assert data[12:16] == bytes([0, 0x04, 0, 32]) and data[-5:] == bytes([0, 0x03, 0, 1, 1])
    assert write_results(bytes([0xFF, 0x0A, 0xFF]), 3) == ["", "object does not exist (0x0a)", ""]


# -- against the S7 PLC --------------------------------------------------------------------------------


async def test_a_bit_written_leaves_its_neighbours(plc: S7PLC) -> None:
    """The request bits share byte 40: writing one (a bit item) keeps the other (the test PLC answers
    bit items as an S7 does; snap7's stock server would overwrite the byte)."""
    await plc.switch(0, 1, True)  # frozen: nothing takes the requests
    await plc.put(0, "Command.UnitModeChangeRequest", True)
    await plc.put(0, "Command.CmdChangeRequest", True)
    assert await plc.tag(0, "Command.UnitModeChangeRequest") is True
    assert await plc.tag(0, "Command.CmdChangeRequest") is True
    await plc.put(0, "Command.CmdChangeRequest", False)
    assert await plc.tag(0, "Command.UnitModeChangeRequest") is True


async def test_config_check_connect_names_an_address_the_plc_does_not_have(tmp_path: Path, plc: S7PLC) -> None:
    text = shipped_cell(plc).replace(
        "start = 200 }",
        'start = 200, alarms = 2, map = { "Admin.StopReason" = "DB9.DBD0", "Admin.Alarm[1].ID" = "DB1.DBD9000" } }',
    )
    path = tmp_path / "cell.toml"
    path.write_text(text)
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    bad = [ln for ln in lines if "PROBLEM" in ln]
    assert len(bad) == 2 and all(ln.startswith("Labeler") for ln in bad), lines
    assert "Admin.StopReason" in bad[0] and "PROBLEM: DB9.DBD0 DINT: Object does not exist (0x0a)" in bad[0], bad
    assert "Admin.Alarm[1].ID" in bad[1] and "DB1.DBD9000 DINT: Invalid address (0x05)" in bad[1], bad
    assert any(ln.startswith("Capper") and "Status.StateCurrent" in ln and "= 2" in ln for ln in lines), lines
    assert "connect: 34 of 36 as configured" in proc.stdout, proc.stdout  # 17 + 19 tags (2 alarms)
    # served: both optional, so the unit works
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        res = await call_path(client, machines(L)[1], "Reset")
        assert res.StatusCode.is_good(), res.StatusCode
        await until(lambda: plc.tag(200, "Status.StateCurrent"), 4)


def test_units_on_one_plc_must_agree_on_the_connection() -> None:
    """One connection per PLC (host, port, rack, slot): a second unit on it with another poll interval
    is refused, naming the unit and the setting; another slot is another PLC (its own connection)."""
    from uacell.gateway.link import SharedLinks
    from uacell.gateway.packml_s7 import S7TagLink

    pool = SharedLinks()

    def get(part: str, settings: dict[str, Any]) -> Any:
        w = where(part, {"host": "plc"} | settings)
        key = (w.host, w.port, w.rack, w.slot)
        return pool.link(part, key, w.interval, w.timeout, lambda: S7TagLink(S7Connection(*key, w.timeout), w.interval))

    first = get("Capper", {"start": 0})
    assert get("Labeler", {"start": 200}) is first
    with pytest.raises(ValueError, match=r"Filler: interval: another unit on s7://plc:102 rack 0 slot 1 set 0\.05"):
        get("Filler", {"start": 400, "interval": 0.2})
    assert get("Other", {"slot": 2, "interval": 0.2}) is not first
    assert first.users == 2


async def test_a_connect_cancelled_half_way_leaves_no_socket_open() -> None:
    """A link closing while it connects cancels the connect after the TCP connection was made and
    before the PLC answered the ISO handshake: the socket is closed then, not left for the collector
    (python-snap7 closes its stream on errors only). The PLC here accepts and never answers."""
    accepted: asyncio.Queue[asyncio.StreamReader] = asyncio.Queue()
    writers: list[asyncio.StreamWriter] = []

    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writers.append(writer)
        await accepted.put(reader)

    port = free_port()
    server = await asyncio.start_server(silent, "127.0.0.1", port)
    try:
        conn = S7Connection("127.0.0.1", port, 0, 1, 30.0)
        connecting = asyncio.ensure_future(conn.connect())
        reader = await asyncio.wait_for(accepted.get(), 10)
        await asyncio.wait_for(reader.read(4), 10)  # the ISO connection request arrived: snap7 waits now
        connecting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await connecting
        assert not conn.connected
        rest = await asyncio.wait_for(reader.read(), 5)  # EOF: the client closed its socket
        assert isinstance(rest, bytes)
    finally:
        for w in writers:
            w.close()
        server.close()
        await server.wait_closed()


@pytest.mark.parametrize("ended_by", ["timeout", "cancel"])
async def test_a_close_whose_disconnect_hangs_still_closes_the_socket(plc: S7PLC, ended_by: str) -> None:
    """python-snap7 forgets its stream without closing it when its disconnect is cut short: a close
    ended by its one-second bound, or by the cancellation of the task that closes the link, still
    closes the socket (a stream nobody closed is a socket left for the collector)."""
    from uacell.gateway import packml_s7

    conn = S7Connection("127.0.0.1", plc.port, 0, 1, 3.0)
    assert await conn.connect()
    client = conn._client
    assert client is not None
    writer = packml_s7._stream(client)
    assert writer is not None and not writer.is_closing()
    hanging = asyncio.Event()

    async def disconnect_that_hangs() -> int:  # a DR whose drain never ends (a peer that reads nothing)
        hanging.set()
        await asyncio.Event().wait()
        return 0

    client.disconnect = disconnect_that_hangs  # type: ignore[method-assign]
    closing = asyncio.ensure_future(conn.close())
    await asyncio.wait_for(hanging.wait(), 5)
    if ended_by == "cancel":
        closing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await closing
    else:
        await asyncio.wait_for(closing, 5)  # the close's own bound: about a second
    assert writer.is_closing()
    assert not conn.connected
