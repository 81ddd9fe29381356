"""The Robotics binding's pure parts: equipment from configuration, samples on first start, the library."""

from __future__ import annotations

import sys
import types

import pytest

from uacell.errors import ConfigError
from uacell.robotics.binding import StoreLibrary, install_samples, make_equipment
from uacell.robotics.config import RobotConfig
from uacell.robotics.model import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot
from uacell.ua.file_store import TEMP_PREFIX, FileStore


def test_time_scale_above_one_makes_the_simulator_faster():
    robot = make_equipment(RobotConfig(time_scale=20.0))
    assert isinstance(robot, SimulatedRobot)
    assert robot.time_scale == pytest.approx(0.05)  # real seconds per simulated second


def test_equipment_factory_is_called_with_the_robot_section(monkeypatch):
    made = []
    module = types.ModuleType("fake_robot_driver")
    module.make = lambda cfg: made.append(cfg) or "driver"
    monkeypatch.setitem(sys.modules, "fake_robot_driver", module)
    cfg = RobotConfig(equipment="fake_robot_driver:make")
    assert make_equipment(cfg) == "driver"
    assert made == [cfg]
    with pytest.raises(ConfigError):
        make_equipment(RobotConfig(equipment="fake_robot_driver:missing"))


def test_samples_are_installed_only_when_the_directory_does_not_exist(tmp_path):
    root = tmp_path / "programs"
    assert install_samples(root) is True
    assert sorted(p.name for p in root.iterdir()) == ["gripper.robot", "palletize.robot", "pick_and_place.robot"]
    (root / "palletize.robot").unlink()
    assert install_samples(root) is False  # a user's deletion stays deleted
    assert not (root / "palletize.robot").exists()


def test_store_library_resolves_names_and_hides_temporary_files(tmp_path):
    root = tmp_path / "programs"
    install_samples(root)
    (root / "sub").mkdir()
    (root / "sub" / "extra.robot").write_text("program Extra\nwait 1\n", encoding="utf-8")
    (root / "notes.txt").write_text("not a program", encoding="utf-8")
    store = FileStore(root)
    # what a directory Delete leaves for a moment: a hidden temporary tree that may hold programs
    ghost = root / f"{TEMP_PREFIX}x" / "d"
    ghost.mkdir(parents=True)
    (ghost / "ghost.robot").write_text("program Ghost\nwait 1\n", encoding="utf-8")
    assert "ghost" in DirectoryLibrary(root).names()  # a plain directory walk would offer it
    library = StoreLibrary(store)
    assert library.names() == ["extra", "gripper", "palletize", "pick_and_place"]
    assert library.resolve("extra") == "sub/extra.robot"
    assert library.resolve("ghost") is None
    assert library.resolve("notes") is None
    assert library.read("sub/extra.robot").startswith("program Extra")
