"""The larger example cell through a real asyncua client: every part on its own.

Two robots (one with two controllers of two task controls each, a seven-axis arm) and three PackML
units at different speeds, as shipped in ``cells/example.toml``.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
import pytest_asyncio
from asyncua import ua
from conftest import fast_config, start_app
from helpers import CellClient, raw_call

from uacell.config import Config, load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.server import UacellServer

pytestmark = pytest.mark.asyncio(loop_scope="module")

TIMEOUT = 30.0
CTRL_A = "Welder.Controllers.ControllerA"
CTRL_B = "Welder.Controllers.ControllerB"
HANDLER = "Handler.Controllers.Controller1"
TASKS = {
    "A/Seam": f"{CTRL_A}.TaskControls.Seam",
    "A/Service": f"{CTRL_A}.TaskControls.Service",
    "B/Seam": f"{CTRL_B}.TaskControls.Seam",
    "B/Cleaning": f"{CTRL_B}.TaskControls.Cleaning",
    "Handler/Palletize": f"{HANDLER}.TaskControls.Palletize",
}
UNITS = ("Filler", "Capper", "Labeler")
RESOURCE = ua.StatusCodes.BadResourceUnavailable


def example_config(data_dir: Path) -> Config:
    config = fast_config(data_dir)
    config.cell = load_cell(builtin_cell_path("example"))
    return config


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory):
    server = await start_app(example_config(tmp_path_factory.mktemp("example") / "data"))
    try:
        yield server
    finally:
        await server.stop()


class Session(CellClient):
    def __init__(self, app: UacellServer, uri: str = "urn:test:cell") -> None:
        super().__init__(app.endpoint, uri, watchdog_intervall=30.0)  # loaded machines: no 1 s probe

    async def read(self, path: str):
        return await self.node(path).read_value()

    async def text(self, path: str) -> str | None:
        dv = await self.node(path).read_data_value(raise_on_bad_status=False)
        return dv.Value.Value.Text if dv.StatusCode.is_good() else None

    async def call(self, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
        return await raw_call(self.client, ua.NodeId(obj, self.ns), ua.NodeId(f"{obj}.{method}", self.ns), *args)

    async def status(self, obj: str, method: str, *args: ua.Variant) -> int | ua.StatusCode:
        res = await self.call(obj, method, *args)
        return res.OutputArguments[0].Value if res.StatusCode.is_good() and res.OutputArguments else res.StatusCode

    async def wait_text(self, path: str, wanted: str) -> None:
        deadline = time.monotonic() + TIMEOUT
        while (got := await self.text(path)) != wanted:
            assert time.monotonic() < deadline, f"{path}: waited for {wanted}, got {got}"
            await asyncio.sleep(0.05)

    async def snapshot(self) -> dict[str, object]:
        """Every task control's and unit's visible state."""
        out: dict[str, object] = {}
        for key, tc in TASKS.items():
            sm = f"{tc}.TaskControlOperation.TaskControlStateMachine"
            out[key] = (
                await self.text(f"{sm}.CurrentState"),
                await self.read(f"{tc}.ParameterSet.TaskProgramName"),
                await self.read(f"{tc}.ParameterSet.TaskProgramLoaded"),
                await self.read(f"{tc}.ParameterSet.ExecutionMode"),
            )
        for ctrl in (CTRL_A, CTRL_B, HANDLER):
            out[ctrl] = await self.text(f"{ctrl}.SystemOperation.SystemOperationStateMachine.CurrentState")
        for unit in UNITS:
            base = f"{unit}.BaseStateMachine"
            out[unit] = (
                await self.text(f"{base}.CurrentState"),
                await self.text(f"{base}.MachineState.CurrentState"),
                await self.read(f"{unit}.Status.MachSpeed"),
                await self.read(f"{unit}.Status.UnitModeCurrent"),
            )
        return out


def s(value: str) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.String)


async def test_each_part_has_its_configured_behaviour(app):
    async with Session(app) as c:
        modes = {k: await c.read(f"{tc}.ParameterSet.ExecutionMode") for k, tc in TASKS.items()}
        assert modes == {"A/Seam": 0, "A/Service": 2, "B/Seam": 0, "B/Cleaning": 1, "Handler/Palletize": 0}
        sm_a = f"{TASKS['A/Seam']}.TaskControlOperation.TaskControlStateMachine"
        assert await c.read(f"{sm_a}.ConfiguredDefaultStopMode") == 4  # QuickStop
        assert [m.Value for m in await c.read(f"{sm_a}.PossibleStopModes")] == [1, 4, 2]
        so_a = f"{CTRL_A}.SystemOperation.SystemOperationStateMachine"
        assert await c.read(f"{so_a}.ConfiguredDefaultStopMode") == 4
        sm_b = f"{TASKS['B/Seam']}.TaskControlOperation.TaskControlStateMachine"
        assert [m.Value for m in await c.read(f"{sm_b}.PossibleStopModes")] == [1, 2, 3, 4, 5]
        assert await c.read(f"{sm_b}.ConfiguredDefaultStopMode") == 1
        for unit, speed, design, low, high, mode in (
            ("Filler", 60.0, 120.0, 0.0, 200.0, 1),
            ("Capper", 180.0, 300.0, 0.0, 400.0, 1),
            ("Labeler", 600.0, 900.0, 100.0, 1200.0, 2),
        ):
            assert await c.read(f"{unit}.Status.MachSpeed") == pytest.approx(speed)
            assert await c.read(f"{unit}.Admin.MachDesignSpeed") == pytest.approx(design)
            rng = await c.read(f"{unit}.Status.MachSpeed.EURange")
            assert (rng.Low, rng.High) == (low, high)
            assert await c.read(f"{unit}.Status.UnitModeCurrent") == mode


async def test_each_controller_has_its_own_programs_directory(app):
    root = Path(app.data_dir) / "programs"
    assert sorted(p.name for p in (root / "Welder" / "ControllerA").iterdir()) == [
        "gripper.robot",
        "palletize.robot",
        "pick_and_place.robot",
    ]
    assert [p.name for p in (root / "Welder" / "ControllerB").iterdir()] == ["wave.robot"]  # seven axes
    assert (root / "Handler" / "Controller1" / "pick_and_place.robot").is_file()
    async with Session(app) as c:
        for ctrl, expected in (
            (CTRL_A, {"gripper.robot", "palletize.robot", "pick_and_place.robot"}),
            (CTRL_B, {"wave.robot"}),
        ):
            children = await c.node(f"{ctrl}.Programs").get_children()
            names = {(await n.read_browse_name()).Name for n in children}
            assert expected <= names and not ({"wave.robot", "gripper.robot"} - expected) & names


async def test_an_operation_on_one_task_control_leaves_every_other_part_untouched(app):
    async with Session(app) as c:
        before = await c.snapshot()
        arm_a = [await c.read(f"Welder.MotionDevices.ArmA.Axes.Axis{i}.ParameterSet.ActualPosition") for i in (1, 2)]
        so_b = f"{CTRL_B}.SystemOperation.SystemOperationStateMachine"
        sm = f"{TASKS['B/Seam']}.TaskControlOperation.TaskControlStateMachine"
        assert await c.status(so_b, "GetReady") == 0
        await c.wait_text(f"{so_b}.CurrentState", "Ready")
        assert await c.status(sm, "LoadByName", s("wave")) == 0
        assert await c.status(sm, "Start") == 0
        j1 = "Welder.MotionDevices.ArmB.Axes.J1.ParameterSet.ActualPosition"
        deadline = time.monotonic() + TIMEOUT
        while await c.read(j1) == 0.0:
            assert time.monotonic() < deadline, "ArmB does not move"
            await asyncio.sleep(0.05)
        after = await c.snapshot()
        assert after.pop("B/Seam")[1:3] == ("Wave", True)
        assert after.pop(CTRL_B) == "Executing"  # SystemOperation follows its running task control
        before.pop("B/Seam")
        before.pop(CTRL_B)
        assert after == before  # the same task control name on ControllerA, the other robot, every unit
        assert [
            await c.read(f"Welder.MotionDevices.ArmA.Axes.Axis{i}.ParameterSet.ActualPosition") for i in (1, 2)
        ] == arm_a
        assert await c.status(sm, "Stop", ua.Variant(4, ua.VariantType.Int64)) == 0  # QuickStop
        await c.wait_text(f"{sm}.CurrentState", "Ready")
        assert await c.status(sm, "UnloadProgram") == 0
        assert await c.status(so_b, "StandDown") == 0
        await c.wait_text(f"{so_b}.CurrentState", "Idle")


async def test_a_lock_on_one_controller_does_not_block_another(app):
    async with Session(app, "urn:test:a") as a, Session(app, "urn:test:b") as b:
        assert (await a.call(f"{CTRL_A}.Lock", "InitLock", s("welding"))).OutputArguments[0].Value == 0
        try:
            so = "SystemOperation.SystemOperationStateMachine"
            sm = "TaskControlOperation.TaskControlStateMachine"
            assert (await b.call(f"{CTRL_A}.{so}", "GetReady")).StatusCode.value == RESOURCE
            assert (await b.call(f"{TASKS['A/Seam']}.{sm}", "LoadByName", s("nothing"))).StatusCode.value == RESOURCE
            # ControllerB (same robot, a task control of the same name) and the other robot are free.
            assert (await b.call(f"{TASKS['B/Seam']}.{sm}", "LoadByName", s("nothing"))).StatusCode.is_good()
            assert (await b.call(f"{TASKS['Handler/Palletize']}.{sm}", "LoadByName", s("nothing"))).StatusCode.is_good()
            assert await b.read(f"{CTRL_B}.Lock.Locked") is False
            assert await b.read(f"{CTRL_A}.Lock.Locked") is True
            assert (await b.call(f"{CTRL_B}.Lock", "InitLock", s("other"))).OutputArguments[0].Value == 0
            assert (await b.call(f"{CTRL_B}.Lock", "ExitLock")).OutputArguments[0].Value == 0
        finally:
            await a.call(f"{CTRL_A}.Lock", "ExitLock")


async def _produce(c: Session, units: tuple[str, ...], until: int) -> tuple[dict[str, int], dict[str, int]]:
    """Reset and Start ``units`` at their configured speeds until the first has made ``until``; the
    totals, and what each made in one window while all of them produced (from the first's first
    package on): start-up takes each unit its own time, the window compares their speeds alone."""
    for unit in units:
        assert (await c.call(f"{unit}.BaseStateMachine.MachineState", "Reset")).StatusCode.is_good()
    for unit in units:
        await c.wait_text(f"{unit}.BaseStateMachine.MachineState.ExecuteState.CurrentState", "Idle")
    for unit in units:
        start = ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)
        res = await c.call(f"{unit}.BaseStateMachine.MachineState.ExecuteState", "Start", start)
        assert res.StatusCode.is_good(), (unit, res.StatusCode)
    deadline = time.monotonic() + TIMEOUT

    async def made() -> dict[str, int]:
        return {u: (await c.read(f"{u}.Admin.ProdProcessedCount"))[0].Count for u in units}

    while min((first := await made()).values()) < 1:  # every unit producing
        assert time.monotonic() < deadline, f"not every one of {units} produces"
        await asyncio.sleep(0.05)
    while (last := await made())[units[0]] < max(until, first[units[0]] + until - 1):
        assert time.monotonic() < deadline, f"{units[0]} does not produce"
        await asyncio.sleep(0.05)
    window = {u: last[u] - first[u] for u in units}
    for unit in units:
        assert (await c.call(f"{unit}.BaseStateMachine.MachineState", "Stop")).StatusCode.is_good()
    for unit in units:
        await c.wait_text(f"{unit}.BaseStateMachine.MachineState.CurrentState", "Stopped")
    return {u: (await c.read(f"{u}.Admin.ProdProcessedCount"))[0].AccCount for u in units}, window


@pytest.mark.asyncio(loop_scope="function")
async def test_two_units_produce_at_their_own_speeds_and_keep_their_admin_data_across_a_restart(tmp_path):
    data = tmp_path / "data"
    app = await start_app(example_config(data))
    try:
        # One task ticks the three units (not one task each).
        assert [t.get_name() for t in asyncio.all_tasks() if t.get_name().startswith("packml")] == ["packml-tick"]
        async with Session(app) as c:
            await c.client.load_data_type_definitions()
            counts, window = await _produce(c, ("Filler", "Capper"), until=3)  # 60 and 180 packages/min
            labeler = (await c.read("Labeler.Admin.ProdProcessedCount"))[0].AccCount
    finally:
        await app.stop()
    assert counts["Filler"] >= 3
    # Three times as fast while both produce (a package either side of the window's edges).
    assert 3 * window["Filler"] - 3 <= window["Capper"] <= 3 * window["Filler"] + 3, window
    assert labeler == 0
    assert sorted(p.name for p in (data / "packml").glob("*.json")) == ["Capper.json", "Filler.json", "Labeler.json"]
    app = await start_app(example_config(data))
    try:
        async with Session(app) as c:
            await c.client.load_data_type_definitions()
            again = {u: (await c.read(f"{u}.Admin.ProdProcessedCount"))[0].AccCount for u in ("Filler", "Capper")}
            assert again == counts
            assert (await c.read("Labeler.Admin.ProdProcessedCount"))[0].AccCount == 0
    finally:
        await app.stop()
