"""Real equipment plugs in through `[robot] equipment` / `[packml] equipment` factories."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from asyncua import Client, ua
from conftest import fast_config, free_port, start_app
from helpers import robot_cell

from uacell.config import load_factory
from uacell.errors import ConfigError
from uacell.packml.binding import UNITS

DRIVER = textwrap.dedent(
    """
    from uacell.packml.equipment import InstantEquipment

    made = []

    class PlantFiller(InstantEquipment):
        pass

    def make(config):
        made.append(config)
        return PlantFiller()

    from uacell.robotics.sim import SimulatedRobot

    class PlantRobot(SimulatedRobot):
        pass

    def make_robot(config):
        made.append(config)
        return PlantRobot(time_scale=0.05)
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
    (tmp_path / "plant_driver.py").write_text(DRIVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    config = fast_config(tmp_path / "data")
    config.packml.equipment = "plant_driver:make"
    config.robot.equipment = "plant_driver:make_robot"
    app = await start_app(config)
    try:
        import plant_driver

        unit = app.registry(UNITS)["Filler1"].unit
        assert type(unit.equipment).__name__ == "PlantFiller"
        assert plant_driver.made == [config.packml, config.robot] or plant_driver.made == [config.robot, config.packml]
        assert type(robot_cell(app).equipment).__name__ == "PlantRobot"
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            machine = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState", ns))
            await machine.call_method(await machine.get_child(f"{await _packml_ns(client)}:Reset"))
            execute = client.get_node(ua.NodeId("Filler1.BaseStateMachine.MachineState.ExecuteState.CurrentState", ns))
            # InstantEquipment completes Resetting at once: the next tick shows Idle.
            for _ in range(100):
                if (await execute.read_value()).Text == "Idle":
                    break
                await app.settle()
                await __import__("asyncio").sleep(0.05)
            assert (await execute.read_value()).Text == "Idle"
    finally:
        await app.stop()


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
    assert len(lines) == 1 and "[packml] equipment 'surely_missing_module_x:make' cannot be loaded" in lines[0]
