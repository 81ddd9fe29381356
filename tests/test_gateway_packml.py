"""PackML units whose state machine runs in a PLC, served by uacell from the cell file alone (the
opcua-packtags driver): node-opcua's server holds the PackTags and runs a TR88 scan-cycle program
(interop/plc_packtags.js) on a free port; an asyncua client drives uacell, which drives the PLC."""

from __future__ import annotations

import asyncio
import os
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import call_path, cell_executable, cell_status, config_check_connect, free_port, until
from helpers import cell_read as read
from helpers import cell_state as state
from helpers import packml_params as params

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.server import UacellServer

pytestmark = pytest.mark.interop
INTEROP = Path(__file__).resolve().parents[1] / "interop"
F = "Capper"
BASE = f"{F}.BaseStateMachine"
MACH = f"{BASE}.MachineState"
EXEC = f"{MACH}.ExecuteState"


class PLC:
    def __init__(self, units: list[str], acting_ms: int = 100, env: dict[str, str] | None = None) -> None:
        self.port, self.units, self.acting_ms = free_port(), units, acting_ms
        self.env = env or {}
        self.proc: subprocess.Popen[str] | None = None
        self.client: Client | None = None

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.port}/"

    def start(self) -> None:
        cmd = ["node", str(INTEROP / "plc_packtags.js"), str(self.port), ",".join(self.units), str(self.acting_ms)]
        self.proc = subprocess.Popen(
            cmd, cwd=INTEROP, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=os.environ | self.env
        )
        assert self.proc.stdout is not None
        deadline = time.monotonic() + 60
        for line in self.proc.stdout:
            if line.strip() == "listening":
                return
            assert time.monotonic() < deadline
        raise RuntimeError("the PLC did not start")

    def new_client(self) -> Client:
        """A client of the PLC's server for the test's own reads and writes. Its health probe gets 30 s,
        not asyncua's 1 s: a read that waits behind a burst on a loaded machine must not drop it."""
        return Client(self.endpoint, timeout=10, watchdog_intervall=30.0)

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
            self.proc = None

    async def tag(self, unit: str, path: str) -> Any:
        assert self.client is not None
        return await self.client.get_node(ua.NodeId(f"{unit}.PackTags.{path}", 1)).read_value()

    async def set(self, unit: str, path: str, value: Any, vtype: ua.VariantType) -> None:
        assert self.client is not None
        await self.client.get_node(ua.NodeId(f"{unit}.PackTags.{path}", 1)).write_value(ua.Variant(value, vtype))


def cell(plc: PLC, units: list[str], extra: str = "") -> str:
    return "".join(
        f"""
[[packml_units]]
name = "{u}"
equipment = {{ driver = "opcua-packtags", endpoint = "{plc.endpoint}", prefix = "ns=1;s={u}.PackTags"{extra} }}
"""
        for u in units
    )


@pytest.fixture
async def plc() -> AsyncIterator[PLC]:
    p = PLC([F])
    p.start()
    try:
        async with p.new_client() as client:
            p.client = client
            yield p
            p.client = None
    finally:
        p.kill()


@pytest.fixture
async def served(tmp_path: Path, plc: PLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    path = tmp_path / "cell.toml"  # the shipped example, nothing changed but the PLC's port
    path.write_text(builtin_cell_path("packtags-unit").read_text().replace(":4841/", f":{plc.port}/"))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as s:
        await s[1].load_data_type_definitions()
        yield s


async def reset_and_start(client: Client, parameters: ua.Variant) -> None:
    """Reset, then Start with ``parameters``, each answered Good and the PLC's state followed."""
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: state(client, EXEC), "Idle")
    res = await call_path(client, EXEC, "Start", parameters)
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: state(client, EXEC), "Execute")


async def test_a_full_cycle_goes_to_the_plc_and_comes_back(served, plc: PLC) -> None:
    _app, client = served
    assert await plc.tag(F, "Status.StateCurrent") == 2  # Stopped
    assert await state(client, MACH) == "Stopped"
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(F, "Status.StateCurrent") in (15, 4)  # the PLC took it before the call answered
    await until(lambda: state(client, EXEC), "Idle")
    assert (await call_path(client, F, "SetMachSpeed", ua.Variant(120.0, ua.VariantType.Float))).StatusCode.is_good()
    await until(lambda: plc.tag(F, "Command.MachSpeed"), 120.0)
    res = await call_path(client, EXEC, "Start", params((1, 180.5), (2, 0.25)))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(F, "Sim.Parameters") == pytest.approx([180.5, 0.25, 0.0, 0.0, 0.0])
    await until(lambda: state(client, EXEC), "Execute")
    # production: the PLC's count, mirrored into Admin.ProdProcessedCount
    await until(lambda: plc_count_positive(client), True)
    assert (await call_path(client, MACH, "Stop")).StatusCode.is_good()
    await until(lambda: state(client, MACH), "Stopped")
    assert await plc.tag(F, "Status.StateCurrent") == 2
    # uacell's own rules before the PLC's: Start is not allowed in Stopped, nothing is written
    res = await call_path(client, EXEC, "Start", params())
    assert res.StatusCode.value in (ua.StatusCodes.BadInvalidState, ua.StatusCodes.BadMethodInvalid)
    assert await plc.tag(F, "Command.CntrlCmd") == 3  # still the Stop


async def plc_count_positive(client: Client) -> bool:
    (count,) = await read(client, f"{F}.Admin.ProdProcessedCount")
    return bool(count.Count > 0)


async def test_a_command_the_plc_refuses_or_never_takes(served, plc: PLC) -> None:
    _app, client = served
    await plc.set(F, "Sim.Refuse", True, ua.VariantType.Boolean)
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await state(client, MACH) == "Stopped" and await plc.tag(F, "Status.StateCurrent") == 2
    await plc.set(F, "Sim.Refuse", False, ua.VariantType.Boolean)
    await plc.set(F, "Sim.Frozen", True, ua.VariantType.Boolean)
    started = time.monotonic()
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadTimeout
    assert time.monotonic() - started >= 2.5  # confirm_timeout 3 s
    assert await plc.tag(F, "Command.CmdChangeRequest") is False  # nothing left half-written
    assert await state(client, MACH) == "Stopped"


async def test_the_plc_faults_and_uacell_aborts_with_its_stop_reason(served, plc: PLC) -> None:
    _app, client = served
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: state(client, EXEC), "Idle")
    await plc.set(F, "Sim.Fault", True, ua.VariantType.Boolean)
    await until(lambda: state(client, BASE), "Aborted")

    async def stop_reason() -> int:
        return int((await read(client, f"{F}.Admin.StopReason")).ID)

    # StopReason is a stored value: clients see it once it is durable, a few ms after the state
    # (docs/packml.md, "Admin variables")
    await until(stop_reason, 42)


async def test_the_plc_killed_and_back(served, plc: PLC) -> None:
    app, client = served
    plc.client = None
    plc.kill()
    ns = await client.get_namespace_index("urn:uacell:cell")

    def executable() -> Any:
        return cell_executable(client, f"{MACH}.Reset")

    await until(executable, False)
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError

    def speed_status() -> Any:
        return cell_status(client, f"{F}.Status.MachSpeed")

    await until(speed_status, "BadNoCommunication")  # the PLC's values are not current any more
    counts = client.get_node(ua.NodeId(f"{F}.Admin.ProdProcessedCount", ns))
    assert (await counts.read_data_value(raise_on_bad_status=False)).StatusCode.name == "BadNoCommunication"
    warnings = client.get_node(ua.NodeId(f"{F}.Admin.Warning", ns))
    assert any(w.ID == 9001 for w in await warnings.read_value())  # uacell's own: readable, says why
    lost = client.get_node(ua.NodeId(f"{F}.Conditions.CommunicationLost.ActiveState.Id", ns))
    assert await lost.read_value() is True  # and the alarm condition alarm clients see
    plc.port = plc.port  # the same port
    plc.start()
    back = time.monotonic()
    await until(executable, True)
    assert time.monotonic() - back <= 5.0
    await until(speed_status, "Good")
    assert not any(w.ID == 9001 for w in await warnings.read_value())  # the warning went with the loss
    await until(lost.read_value, False)
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    assert app is not None


async def test_fifty_units_on_one_plc_connection(tmp_path: Path) -> None:
    units = [f"U{i}" for i in range(1, 51)]
    p = PLC(units)
    p.start()
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, units))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client), p.new_client() as plc_client:
            p.client = plc_client
            from uacell.gateway.packml_opcua import POOL

            assert len(POOL) == 1  # one connection to the PLC

            async def reset(u: str) -> str:
                return str((await call_path(client, f"{u}.BaseStateMachine.MachineState", "Reset")).StatusCode.name)

            results = dict(zip(units, await asyncio.gather(*(reset(u) for u in units)), strict=True))  # all at once
            bad = {u: r for u, r in results.items() if r != "Good"}
            assert not bad, bad
            for u in units:
                await until(lambda u=u: state(client, f"{u}.BaseStateMachine.MachineState.ExecuteState"), "Idle")
            # nothing lost: every unit is in Idle in the PLC too
            for u in units:
                assert await p.tag(u, "Status.StateCurrent") == 4
    finally:
        p.kill()


async def test_node_opcua_runs_a_cycle_through_uacell_to_the_plc(tmp_path: Path) -> None:
    """The independent client: node-opcua resets and starts (with two parameters) a unit the PLC owns."""
    from conftest import run_node

    p = PLC(["Filler1"])
    p.start()
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, ["Filler1"]))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (app, _client), p.new_client() as plc_client:
            p.client = plc_client
            out = await asyncio.to_thread(run_node, "packml_start.js", app.endpoint)
            assert (out["reset"], out["start"], out["state"]) == ("Good", "Good", "Execute")
            assert await p.tag("Filler1", "Status.StateCurrent") == 6  # the PLC is in Execute
            assert await p.tag("Filler1", "Sim.Parameters") == pytest.approx([250.5, -12.25, 0.0, 0.0, 0.0])
            p.client = None
    finally:
        p.kill()


async def test_config_check_connect_and_a_tag_of_the_wrong_type(
    tmp_path: Path, plc: PLC, caplog: pytest.LogCaptureFixture
) -> None:
    """`uacell config check --connect` tries every tag and names what it found; served anyway, the
    tag of the wrong type is one log line naming the unit and the tag."""

    wrong = f"ns=1;s={F}.PackTags.Sim.Fault"  # a Boolean where StateCurrent (Int32) belongs
    text = builtin_cell_path("packtags-unit").read_text().replace(":4841/", f":{plc.port}/")
    overrides = f'"Status.StateCurrent" = "{wrong}", "Admin.StopReason" = "ns=1;s=Nope"'
    text = text.replace(
        'prefix = "ns=1;s=Capper.PackTags" }', f'prefix = "ns=1;s=Capper.PackTags", map = {{ {overrides} }} }}'
    )

    path = tmp_path / "cell.toml"
    path.write_text(text)
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert any("Status.StateCurrent" in ln and "PROBLEM: Boolean = False, expected Int32" in ln for ln in lines), lines
    assert any("Admin.StopReason" in ln and "PROBLEM: ns=1;s=Nope: BadNodeIdUnknown" in ln for ln in lines), lines
    assert any("Command.CntrlCmd" in ln and "Int32 = 0" in ln and "PROBLEM" not in ln for ln in lines), lines
    assert "connect: 15 of 17 as configured" in proc.stdout
    # served anyway: one log line names the unit, the tag and what it holds; the state is not followed
    served = tmp_path / "served.toml"
    served.write_text(text.replace(', "Admin.StopReason" = "ns=1;s=Nope"', ""))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(served)
    async with serving(config) as (_app, client):
        assert await state(client, MACH) == "Stopped"
        found = [r.getMessage() for r in caplog.records if "Status.StateCurrent" in r.getMessage()]
        assert found and f"{F}: Status.StateCurrent ({wrong}) holds False, not a Int32" in found[0]


async def test_unit_mode_changes_go_through_the_plc(served, plc: PLC) -> None:
    _app, client = served
    mode = ua.Variant(2, ua.VariantType.Int32)  # Maintenance
    res = await call_path(client, F, "SetUnitMode", mode)
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(F, "Status.UnitModeCurrent") == 2 and await plc.tag(F, "Command.UnitMode") == 2
    assert await read(client, f"{F}.Status.UnitModeCurrent") == 2
    # not a supported mode: refused by uacell, nothing written to the PLC
    res = await call_path(client, F, "SetUnitMode", ua.Variant(17, ua.VariantType.Int32))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert await plc.tag(F, "Command.UnitMode") == 2
    # the PLC refuses: Bad_InvalidState, the mode stays
    await plc.set(F, "Sim.Refuse", True, ua.VariantType.Boolean)
    res = await call_path(client, F, "SetUnitMode", ua.Variant(1, ua.VariantType.Int32))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await read(client, f"{F}.Status.UnitModeCurrent") == 2
    assert await plc.tag(F, "Command.UnitModeChangeRequest") is False


async def test_a_plc_away_at_start_is_served_and_picked_up_when_it_comes(tmp_path: Path) -> None:
    p = PLC([F])  # not started yet: nothing listens on its port
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, [F]))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client):
            ns = await client.get_namespace_index("urn:uacell:cell")
            speed = client.get_node(ua.NodeId(f"{F}.Status.MachSpeed", ns))

            async def speed_status() -> str:
                return (await speed.read_data_value(raise_on_bad_status=False)).StatusCode.name

            await until(speed_status, "BadNoCommunication")
            res = await call_path(client, MACH, "Reset")
            assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError
            p.start()
            back = time.monotonic()
            await until(speed_status, "Good")
            assert time.monotonic() - back <= 5.0
            assert await read(client, f"{F}.Status.MachSpeed") == pytest.approx(60.0)  # the PLC's value
            res = await call_path(client, MACH, "Reset")
            assert res.StatusCode.is_good(), res.StatusCode
            await until(lambda: state(client, EXEC), "Idle")
    finally:
        p.kill()


async def test_a_secure_plc_with_a_user_polled(tmp_path: Path) -> None:
    """A PLC that offers Basic256Sha256 only and admits one user: uacell signs and encrypts with its
    client certificate, logs in with the password from an owner-only file, and polls the tags."""
    from uacell.security.pki import make_client_certificate

    der, key = make_client_certificate("urn:uacell:test:gateway", common_name="uacell gateway")
    (tmp_path / "gateway.der").write_bytes(der)
    (tmp_path / "gateway-key.pem").write_bytes(key)
    secret = tmp_path / "plc.password"
    secret.write_text("s3cret\n")
    secret.chmod(0o600)
    p = PLC([F], env={"PLC_PKI": str(tmp_path / "plc-pki"), "PLC_USER": "gateway:s3cret"})
    p.start()
    try:
        extra = (
            f', security = "Basic256Sha256,SignAndEncrypt", certificate = "{tmp_path / "gateway.der"}"'
            f', private_key = "{tmp_path / "gateway-key.pem"}", username = "gateway", password_file = "{secret}"'
            ', mode = "poll", interval = 0.05'
        )
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, [F], extra))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client):
            await reset_and_start(client, params((1, 7.5)))
        # the same PLC refuses an anonymous client on a channel without security
        with pytest.raises(Exception):  # noqa: B017 (asyncua raises what the PLC's refusal became)
            async with Client(p.endpoint, timeout=5) as anonymous:
                await anonymous.get_node(ua.NodeId(f"{F}.PackTags.Status.StateCurrent", 1)).read_value()
    finally:
        p.kill()


def test_link_options_refuse_what_cannot_work(tmp_path: Path) -> None:
    from uacell.gateway.opcua_link import link_options

    ok: dict[str, Any] = {"endpoint": "opc.tcp://plc:4840/"}
    assert link_options("Capper", ok).mode == "subscribe"
    assert link_options("Capper", ok).timeout == 2.0
    assert link_options("Capper", ok | {"timeout": 10}).timeout == 10.0
    readable = tmp_path / "pw"
    readable.write_text("x")
    readable.chmod(0o644)
    cases: dict[str, tuple[dict[str, Any], str]] = {
        "endpoint": ({"endpoint": "http://plc"}, "Capper: endpoint"),
        "security": (ok | {"security": "Basic128,Sign"}, "Capper: security: 'Basic128,Sign' is not None"),
        "certificate": (ok | {"security": "Basic256Sha256,Sign"}, "Capper: certificate: a secure channel needs"),
        "password": (ok | {"username": "u", "password_env": "UACELL_TEST_NO_SUCH_VARIABLE"}, "no password"),
        "readable": (ok | {"username": "u", "password_file": str(readable)}, "may be read by others"),
        "mode": (ok | {"mode": "push"}, 'Capper: mode: "subscribe" or "poll"'),
        "interval": (ok | {"interval": 0}, "Capper: interval"),
        "timeout": (ok | {"timeout": 0.01}, "Capper: timeout: seconds between 0.1 and 60, not 0.01"),
        "timeout type": (ok | {"timeout": "2"}, "Capper: timeout: seconds between 0.1 and 60, not '2'"),
        "timeout bool": (ok | {"timeout": True}, "Capper: timeout: seconds between 0.1 and 60, not True"),
    }
    for name, (settings, message) in cases.items():
        with pytest.raises(ValueError, match=None) as info:
            link_options("Capper", settings)
        assert message in str(info.value), (name, str(info.value))


def test_parts_that_give_a_plc_different_timeouts_get_connections_of_their_own() -> None:
    """OPC UA links are shared per connection settings, ``timeout`` among them: the same (given or
    default) shares one connection, another timeout is another connection with that timeout."""
    from uacell.gateway.opcua_link import link_options, link_pool, shared_link

    pool, endpoint = link_pool(), "opc.tcp://plc:4840/"
    capper = shared_link(pool, link_options("Capper", {"endpoint": endpoint}), "Capper")
    labeler = shared_link(pool, link_options("Labeler", {"endpoint": endpoint, "timeout": 2.0}), "Labeler")
    filler = shared_link(pool, link_options("Filler", {"endpoint": endpoint, "timeout": 5}), "Filler")
    assert labeler is capper and capper.timeout == 2.0
    assert filler is not capper and filler.timeout == 5.0 and len(list(pool.values())) == 2


async def test_the_plc_changes_its_unit_mode_and_alarms_by_itself(tmp_path: Path) -> None:
    p = PLC([F])
    p.start()
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(p, [F], ", alarms = 2"))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client), p.new_client() as plc_client:
            await client.load_data_type_definitions()
            p.client = plc_client
            assert await read(client, f"{F}.Status.UnitModeCurrent") == 1
            await p.set(F, "Status.UnitModeCurrent", 2, ua.VariantType.Int32)  # the key switch on its panel
            await until(lambda: read(client, f"{F}.Status.UnitModeCurrent"), 2)

            async def alarms() -> list[int]:
                return [a.ID for a in await read(client, f"{F}.Admin.Alarm")]

            await p.set(F, "Admin.Alarm[1].ID", 77, ua.VariantType.Int32)
            await until(alarms, [77])
            await p.set(F, "Admin.Alarm[0].ID", 12, ua.VariantType.Int32)
            await until(alarms, [77, 12])
            await p.set(F, "Admin.Alarm[1].ID", 0, ua.VariantType.Int32)  # cleared in the PLC
            await until(alarms, [12])

            async def history() -> list[tuple[int, bool]]:  # durable: published once stored
                return [(h.ID, h.Trigger) for h in await read(client, f"{F}.Admin.AlarmHistory") if h.ID in (12, 77)]

            await until(history, [(77, False), (12, True)])  # 77 acknowledged when the PLC cleared it
            assert await state(client, f"{MACH}") is not None
            p.client = None
    finally:
        p.kill()


async def test_tags_by_browse_path(tmp_path: Path) -> None:
    """prefix = "/1:Capper/1:PackTags": each tag is found below it by browse names (Command/CntrlCmd,
    Command/Parameter[0]/Value ...), translated when uacell connects; an override may be a path too."""
    p = PLC([F])
    p.start()
    try:
        text = cell(p, [F]).replace('prefix = "ns=1;s=Capper.PackTags"', 'prefix = "/1:Capper/1:PackTags"')
        text = text.replace(
            " }\n", ', map = { "Admin.StopReason" = "/1:Capper/1:PackTags/1:Admin/1:StopReason/1:ID" } }\n'
        )
        path = tmp_path / "cell.toml"
        path.write_text(text)
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client), p.new_client() as plc_client:
            p.client = plc_client
            await reset_and_start(client, params((1, 2.5)))
            assert await p.tag(F, "Sim.Parameters") == pytest.approx([2.5, 0.0, 0.0, 0.0, 0.0])
            p.client = None
        # a path the PLC does not have is named by config check --connect
        bad = tmp_path / "bad.toml"
        bad.write_text(text.replace("/1:Admin/1:StopReason/1:ID", "/1:Admin/1:NoSuchTag"))
        proc = await config_check_connect(bad)
        assert proc.returncode == 1 and "Admin.StopReason" in proc.stdout and "BadNoMatch" in proc.stdout, proc.stdout
    finally:
        p.kill()
