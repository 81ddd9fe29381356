"""Real equipment plugs in through `[robot] equipment` / `[packml] equipment` factories."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap
from typing import cast

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import free_port, robot_cell, until

from uacell.config import load_cell, load_factory
from uacell.core.errors import ConfigError
from uacell.packml.binding import UNITS
from uacell.packml.sim import SimulatedUnit
from uacell.server import UacellServer

DRIVER = textwrap.dedent(
    """
    import asyncio

    from uacell.packml.equipment import InstantEquipment
    from uacell.robotics.sim import SimulatedRobot

    made = []
    closed = []

    class PlantFiller(InstantEquipment):
        def __init__(self, spec):
            self.spec = spec

        async def close(self):  # a driver's close hook may be a coroutine
            await asyncio.sleep(0)
            closed.append(self.spec.part)

    async def make(spec):  # a driver that connects at start-up
        await asyncio.sleep(0)
        made.append(spec)
        return PlantFiller(spec)

    class PlantRobot(SimulatedRobot):
        def close(self):
            closed.append("robot")

    def make_robot(spec):
        made.append(spec)
        return PlantRobot(time_scale=0.05, axes=spec.axes)

    def broken(spec):
        raise ConnectionRefusedError("controller 10.0.0.9 does not answer")

    def not_equipment(spec):
        return object()
    """
)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("no_colon", "must look like 'package.module:factory'"),
        ("surely_missing_module_x:make", "cannot be loaded"),
        ("uacell.config:ROLES_MISSING", "cannot be loaded"),
        ("uacell.config:ROLES", "is not callable"),
    ],
)
def test_bad_factory_specs_are_clear_config_errors(spec, message):
    with pytest.raises(ConfigError, match=message):
        load_factory(spec, "packml")


async def test_units_run_on_the_configured_equipment(tmp_path, monkeypatch):
    """The old [robot]/[packml] equipment keys still give every part without its own a factory."""
    _driver(tmp_path, monkeypatch)
    config = fast_config(tmp_path / "data")
    config.packml.equipment = "plant_driver:make"
    config.robot.equipment = "plant_driver:make_robot"
    app = await start_app(config)
    try:
        plant_driver = importlib.import_module("plant_driver")  # written by the test: unknown to the checker

        unit = app.registry(UNITS)["Filler1"].unit
        assert type(unit.equipment).__name__ == "PlantFiller"
        assert sorted(s.part for s in plant_driver.made) == ["Filler1", "Robot1.Controllers.Controller1"]
        robot_spec = next(s for s in plant_driver.made if s.part.startswith("Robot1"))
        assert [a.name for a in robot_spec.axes] == [f"Axis{i}" for i in range(1, 7)]
        assert type(robot_cell(app).equipment).__name__ == "PlantRobot"
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            machine = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState", ns))
            await machine.call_method(await machine.get_child(f"{await _packml_ns(client)}:Reset"))
            execute = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState.ExecuteState.CurrentState", ns))

            # InstantEquipment completes Resetting at once: the next tick shows Idle.
            async def state() -> str:
                await app.settle()
                return str((await execute.read_value()).Text)

            await until(state, "Idle")
    finally:
        await app.stop()
    assert sorted(plant_driver.closed) == ["Filler1", "robot"]  # each driver's close hook ran


CELL = """
[[packml_units]]
name = "Simulated"
acting_time = 0.05

[[packml_units]]
name = "Plant"
equipment = "plant_driver:make"
settings = { address = "10.0.0.7", port = 502, recipe = { size = 3 } }
"""


async def test_each_part_has_its_own_factory_and_settings(tmp_path, monkeypatch):
    _driver(tmp_path, monkeypatch)
    (tmp_path / "cell.toml").write_text(CELL)
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(tmp_path / "cell.toml")
    app = await start_app(config)
    try:
        plant_driver = importlib.import_module("plant_driver")  # written by the test: unknown to the checker

        assert [(s.part, dict(s.settings)) for s in plant_driver.made] == [
            ("Plant", {"address": "10.0.0.7", "port": 502, "recipe": {"size": 3}})
        ]
        assert type(app.registry(UNITS)["Plant"].unit.equipment).__name__ == "PlantFiller"
        assert type(app.registry(UNITS)["Simulated"].unit.equipment).__name__ == "SimulatedUnit"
        assert cast(SimulatedUnit, app.registry(UNITS)["Simulated"].unit.equipment).acting_time == 0.05
    finally:
        await app.stop()
    assert plant_driver.closed == ["Plant"]


@pytest.mark.parametrize(
    ("factory", "message"),
    [
        ("plant_driver:broken", "Plant: equipment 'plant_driver:broken' failed: ConnectionRefusedError: controller"),
        (
            "plant_driver:not_equipment",
            "Plant: equipment 'plant_driver:not_equipment' returned object, not a "
            "PackMLEquipment (missing attach, poll,",
        ),
    ],
)
async def test_a_factory_that_fails_or_returns_no_equipment_stops_start_up_naming_the_part(
    tmp_path, monkeypatch, factory, message
):
    _driver(tmp_path, monkeypatch)
    (tmp_path / "cell.toml").write_text(CELL.replace("plant_driver:make", factory))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(tmp_path / "cell.toml")
    app = UacellServer(config)
    try:
        with pytest.raises(ConfigError) as caught:
            await app.setup()
        assert str(caught.value).startswith(message)
        assert "\n" not in str(caught.value)
    finally:
        await app.stop()


def test_serve_with_a_failing_factory_is_one_line_and_exit_2(tmp_path):
    (tmp_path / "plant_driver.py").write_text(DRIVER)
    (tmp_path / "cell.toml").write_text(CELL.replace("plant_driver:make", "plant_driver:broken"))
    proc = _serve(tmp_path, tmp_path / "cell.toml", env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert proc.returncode == 2
    errors = [line for line in proc.stderr.splitlines() if line.startswith("uacell:")]
    assert errors == [
        "uacell: Plant: equipment 'plant_driver:broken' failed: ConnectionRefusedError: controller 10.0.0.9 does not"
        " answer"
    ]
    assert "Traceback" not in proc.stderr and "listening" not in proc.stdout


def _driver(tmp_path, monkeypatch) -> None:
    """plant_driver importable from tmp_path, freshly imported (its lists empty)."""
    (tmp_path / "plant_driver.py").write_text(DRIVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "plant_driver", raising=False)


def _serve(tmp_path, config, env=None):
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "uacell",
            "--log-level",
            "WARNING",
            "serve",
            "--config",
            str(config),
            "--port",
            str(free_port()),
            "--data-dir",
            str(tmp_path / "d"),
        ],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
        env=env,
    )


async def _packml_ns(client) -> int:
    return await client.get_namespace_index("http://opcfoundation.org/UA/PackML/")


def test_serve_with_unloadable_equipment_is_one_clear_line(tmp_path):
    cfg = tmp_path / "uacell.toml"
    cfg.write_text('[packml]\nequipment = "surely_missing_module_x:make"\n')
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "uacell",
            "serve",
            "--config",
            str(cfg),
            "--port",
            str(free_port()),
            "--data-dir",
            str(tmp_path / "d"),
        ],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "[packml] equipment: 'surely_missing_module_x:make' cannot be loaded" in lines[0]
