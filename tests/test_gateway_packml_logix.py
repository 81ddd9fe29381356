"""PackML units whose state machine runs in a Rockwell Logix controller, served by uacell from the
cell file alone (the logix-packtags driver, pylogix over EtherNet/IP): cpppo's EtherNet/IP Logix
simulator holds the PackTags as Logix tags by name and runs a TR88 scan-cycle program
(uacell.gateway.examples.logix_plc) on a free port; an asyncua client (and node-opcua once) drives
uacell, which drives the controller. cpppo cannot resolve an array index inside a dotted name, so
the simulator's parameters are a top-level array the cell maps (docs/equipment.md says what the
simulator could not cover).

The scenarios every polled PackTags driver passes (a full cycle, a refused and a frozen command, a
fault, the PLC killed and back, node-opcua's cycle) are in test_gateway_packml_acceptance.py; here
is what only this transport has."""

from __future__ import annotations

import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from conftest import fast_config, serving
from gateway_plcs import LogixPLC
from gateway_plcs import logix_cell as shipped_cell
from helpers import (
    call_path,
    config_check_connect,
)

from uacell.config import load_cell
from uacell.gateway.errors import CommunicationError
from uacell.gateway.packml_logix import LogixConnection, where

F = "Capper"
MACH = f"{F}.BaseStateMachine.MachineState"


@pytest.fixture
async def plc() -> AsyncIterator[LogixPLC]:
    p = LogixPLC()
    p.start()
    try:
        await p.open()
        yield p
    finally:
        await p.close()
        p.kill()


def test_tags_by_name_under_the_prefix_and_overrides() -> None:
    w = where(F, {"host": "plc", "prefix": "Capper", "alarms": 1, "map": {"Status.StateCurrent": "Program:Line.State"}})
    assert w.tags["Command.CntrlCmd"].address == "Capper.Command.CntrlCmd"
    assert w.tags["Command.Parameter[2].Value"].address == "Capper.Command.Parameter[2].Value"
    assert w.tags["Admin.Alarm[0].ID"].address == "Capper.Admin.Alarm[0].ID"
    assert w.tags["Admin.StopReason"].address == "Capper.Admin.StopReason.ID"
    assert w.tags["Status.StateCurrent"].address == "Program:Line.State"
    assert (w.port, w.slot) == (44818, 0)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"prefix": "ns=3;s=Capper"}, "Capper: prefix: 'ns=3;s=Capper' is not a Logix tag name"),
        ({"prefix": ""}, "Capper: prefix: empty, and no tag is given in full"),
        ({"map": {"Status.Nope": "X"}}, "Capper: Status.Nope: not a PackTags tag of the map"),
        ({"map": {"Status.StateCurrent": 3}}, "Capper: map: a table of tag = "),
        ({"slot": 40}, "Capper: slot: a whole number from 0 to 31"),
        ({"bogus": 1}, "the logix-packtags driver has no setting 'bogus'"),
    ],
)  # fmt: skip
def test_settings_that_cannot_work_are_one_line(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        where("Capper", {"host": "plc", "prefix": "Capper"} | settings)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


async def test_config_check_connect_names_a_tag_the_controller_does_not_have(tmp_path: Path, plc: LogixPLC) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(
        shipped_cell(plc).replace(
            '"Capper_Parameter[4]" }', '"Capper_Parameter[4]", "Admin.StopReason" = "Capper.Nope" }'
        )
    )
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    bad = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
    assert len(bad) == 1 and "Admin.StopReason" in bad[0] and "Capper.Nope: Path destination unknown" in bad[0], bad
    assert "connect: 16 of 17 as configured" in proc.stdout, proc.stdout
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):  # optional: the unit works
        res = await call_path(client, MACH, "Reset")
        assert res.StatusCode.is_good(), res.StatusCode


async def test_a_request_that_comes_after_close_opens_no_connection() -> None:
    """pylogix reconnects by itself inside Read: a read that waited behind close (its caller gave up
    on it) must neither reach the controller nor leave a socket open."""
    with socket.create_server(("127.0.0.1", 0)) as controller:
        port = controller.getsockname()[1]
        conn = LogixConnection("127.0.0.1", port, 0, timeout=0.5)
        conn.close()
        conn.connected = True  # as a request queued before the close still believes
        with pytest.raises(CommunicationError, match="closed"):
            await conn.read(["Capper.Status.StateCurrent"])
        with pytest.raises(CommunicationError, match="closed"):
            await conn.write([("Capper.Command.CntrlCmd", 2)])
        with pytest.raises(CommunicationError, match="closed"):
            await conn.connect()
        controller.setblocking(False)
        with pytest.raises(BlockingIOError):
            controller.accept()  # nobody connected
