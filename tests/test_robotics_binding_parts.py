"""The Robotics binding's pure parts: equipment from configuration, samples on first start, the library."""

from __future__ import annotations

import sys
import types

import pytest

from uacell.core.equipment_factory import EquipmentSpec, make_equipment
from uacell.core.errors import ConfigError
from uacell.core.file_store import TEMP_PREFIX, FileStore
from uacell.robotics.binding import StoreLibrary, install_samples
from uacell.robotics.binding.programs import adopt_legacy_programs
from uacell.robotics.equipment import AxisInfo, ControllerEquipmentSpec, RobotEquipment
from uacell.robotics.program import wave_program
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot


async def test_time_scale_above_one_makes_the_simulator_faster():
    spec = EquipmentSpec("Robot1.Controllers.Controller1", {"time_scale": 20.0})
    robot = await make_equipment("uacell.robotics.sim:simulator", spec, RobotEquipment)
    assert isinstance(robot, SimulatedRobot)
    assert robot.time_scale == pytest.approx(0.05)  # real seconds per simulated second
    assert [a.name for a in robot.axes] == ["A1", "A2", "A3", "A4", "A5", "A6"]  # no configured axes


async def test_the_simulator_moves_the_configured_axes_and_refuses_unknown_settings():
    axes = tuple(AxisInfo(f"J{i}", -90.0, 90.0, 100.0) for i in range(1, 8))
    spec = ControllerEquipmentSpec("R.Controllers.C", {"power_up_time": 0.5, "alarms": ["Fence"]}, axes)
    robot = await make_equipment("uacell.robotics.sim:simulator", spec, RobotEquipment)
    assert [a.name for a in robot.axes] == [f"J{i}" for i in range(1, 8)]
    assert robot.alarm_names == ("Fence",) and robot.power_up_time == 0.5
    with pytest.raises(ConfigError, match=r"^R.Controllers.C: .* no setting 'colour'"):
        await make_equipment(
            "uacell.robotics.sim:simulator", EquipmentSpec("R.Controllers.C", {"colour": 1}), RobotEquipment
        )


async def test_equipment_factory_is_called_with_the_part_and_its_settings(monkeypatch):
    made = []
    module = types.ModuleType("fake_robot_driver")

    async def connect(spec):  # a driver that connects at start-up
        made.append(spec)
        return SimulatedRobot()

    vars(module)["make"] = connect  # the factory the cell names: fake_robot_driver:make
    monkeypatch.setitem(sys.modules, "fake_robot_driver", module)
    spec = EquipmentSpec("Robot1.Controllers.Controller1", {"address": "10.0.0.5"})
    robot = await make_equipment("fake_robot_driver:make", spec, RobotEquipment)
    assert isinstance(robot, SimulatedRobot)
    assert made == [spec]
    with pytest.raises(ConfigError, match=r"Robot1.Controllers.Controller1\] equipment: .* cannot be loaded"):
        await make_equipment("fake_robot_driver:missing", spec, RobotEquipment)


def test_samples_are_installed_only_when_the_directory_does_not_exist(tmp_path):
    root = tmp_path / "programs"
    assert install_samples(root) is True
    assert sorted(p.name for p in root.iterdir()) == ["gripper.robot", "palletize.robot", "pick_and_place.robot"]
    (root / "palletize.robot").unlink()
    assert install_samples(root) is False  # a user's deletion stays deleted
    assert not (root / "palletize.robot").exists()


def test_a_controller_without_a_motion_device_gets_a_program_without_move(tmp_path):
    from uacell.robotics.program import parse

    root = tmp_path / "programs"
    assert install_samples(root, moves=False) is True
    assert [p.name for p in root.iterdir()] == ["idle.robot"]
    assert parse((root / "idle.robot").read_text(), []).name == "Idle"  # empty limits: no motion device


def test_an_arm_with_other_than_six_axes_gets_a_generated_program_that_fits_it(tmp_path):
    from uacell.robotics.program import parse

    axes = [AxisInfo(f"J{i}", -10.0 * i, 10.0 * i, 90.0) for i in range(1, 8)]
    root = tmp_path / "programs"
    assert install_samples(root, axes) is True
    assert [p.name for p in root.iterdir()] == ["wave.robot"]
    program = parse((root / "wave.robot").read_text(), [a.limits for a in axes])
    moves = [i.joints for i in program.instructions if hasattr(i, "joints")]
    assert len(moves) == 1 + 2 * 7 and all(len(m) == 7 for m in moves)
    assert {m for m in moves if any(m)} == {
        tuple(min(20.0, 5.0 * i) if k == i - 1 else 0.0 for k in range(7)) for i in range(1, 8)
    }
    assert wave_program(axes) == (root / "wave.robot").read_text()


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


def test_programs_of_the_old_single_directory_layout_move_to_the_first_controller(tmp_path):
    programs = tmp_path / "programs"
    (programs / "sub").mkdir(parents=True)
    (programs / "mine.robot").write_text("program Mine\nend\n", encoding="utf-8")
    (programs / "sub" / "part.robot").write_text("module Part\nend\n", encoding="utf-8")
    (programs / "Robot2").mkdir()  # another robot's directory stays where it is
    root = programs / "Robot1" / "Controller1"
    assert adopt_legacy_programs(programs, root, ["Robot1", "Robot2"]) == 2
    assert (root / "mine.robot").read_text(encoding="utf-8") == "program Mine\nend\n"
    assert (root / "sub" / "part.robot").exists()
    assert sorted(p.name for p in programs.iterdir()) == ["Robot1", "Robot2"]
    # Once the controller has its directory, nothing moves again.
    (programs / "late.robot").write_text("program Late\nend\n", encoding="utf-8")
    assert adopt_legacy_programs(programs, root, ["Robot1", "Robot2"]) == 0
    assert (programs / "late.robot").exists()


def test_a_new_layout_without_legacy_program_files_is_left_alone(tmp_path):
    programs = tmp_path / "programs"
    (programs / "Robot1" / "Controller1").mkdir(parents=True)
    root = programs / "Robot1" / "Controller2"
    assert adopt_legacy_programs(programs, root, ["Robot1"]) == 0
    assert not root.exists()


async def test_the_demo_controller_serves_programs_stored_by_an_older_uacell(tmp_path):
    from asyncua import Client
    from conftest import fast_config, start_app

    data = tmp_path / "data"
    (data / "programs").mkdir(parents=True)
    (data / "programs" / "legacy.robot").write_text("program Legacy\nmove 0 0 0 0 0 0\nend\n", encoding="utf-8")
    app = await start_app(fast_config(data))
    try:
        async with Client(app.endpoint) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            programs = client.get_node(f"ns={ns};s=Robot1.Controllers.Controller1.Programs")
            names = {(await c.read_browse_name()).Name for c in await programs.get_children()}
            assert "legacy.robot" in names
    finally:
        await app.stop()


def test_store_library_index_follows_the_listing(tmp_path):
    root = tmp_path / "programs"
    install_samples(root)
    (root / "b").mkdir()
    (root / "b" / "twin.robot").write_text("program TwinB\nwait 1\n", encoding="utf-8")
    store = FileStore(root)
    library = StoreLibrary(store)
    plain = DirectoryLibrary(root)
    assert library.resolve("twin") == plain.resolve("twin") == "b/twin.robot"
    assert library.resolve("later") is None
    # A file added and a name held twice: the index is made again from the new listing, and the
    # same file wins as in a plain directory walk (sorted paths: "a/twin.robot" before "b/...").
    (root / "a").mkdir()
    (root / "a" / "twin.robot").write_text("program TwinA\nwait 1\n", encoding="utf-8")
    (root / "later.robot").write_text("program Later\nwait 1\n", encoding="utf-8")
    assert library.resolve("twin") == plain.resolve("twin") == "a/twin.robot"
    assert library.resolve("later") == "later.robot"
    (root / "later.robot").unlink()
    assert library.resolve("later") is None


def test_library_keeps_a_settled_small_file_text_while_its_status_is_unchanged(tmp_path, monkeypatch):
    import uacell.core.files
    import uacell.robotics.program_cache as model

    root = tmp_path / "programs"
    root.mkdir()
    path = root / "p.robot"
    path.write_text("program One\nwait 1\n", encoding="utf-8")
    library = DirectoryLibrary(root)
    opened: list[str] = []
    real_open = open

    def counting_open(file, *args, **kwargs):
        opened.append(str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(model, "open", counting_open, raising=False)
    # Just written: not settled, read from the disk every time.
    assert library.read("p.robot") == "program One\nwait 1\n"
    assert library.read("p.robot") == "program One\nwait 1\n"
    assert len(opened) == 2
    monkeypatch.setattr(uacell.core.files, "SETTLE_NS", 0)  # everything counts as settled from here
    assert library.read("p.robot") == "program One\nwait 1\n"
    assert library.read("p.robot") == "program One\nwait 1\n"
    assert len(opened) == 3  # kept after the third read
    # Replaced (a new inode, the same size): read again.
    replacement = root / "p.tmp"
    replacement.write_text("program Two\nwait 1\n", encoding="utf-8")
    replacement.replace(path)
    assert library.read("p.robot") == "program Two\nwait 1\n"
    assert len(opened) == 4
    # Written in place with another size: read again.
    path.write_text("program Three\nwait 2\n", encoding="utf-8")
    assert library.read("p.robot") == "program Three\nwait 2\n"
    # Gone: the same error as without the cache.
    path.unlink()
    with pytest.raises(FileNotFoundError):
        library.read("p.robot")
    # A file larger than a program read on the event loop is never kept.
    big = "program Big\n" + "wait 1\n" * 700
    (root / "big.robot").write_text(big, encoding="utf-8")
    opened.clear()
    assert library.read("big.robot") == big
    assert library.read("big.robot") == big
    assert len(opened) == 2
    # What is read on the event loop: a small file's text (kept as above), nothing of a big or missing one.
    assert library.read_small("big.robot") is None
    assert library.read_small("p.robot") is None  # gone: ``read`` (in a worker thread) says why
    (root / "q.robot").write_text("program Q\nwait 1\n", encoding="utf-8")
    assert library.read_small("q.robot") == "program Q\nwait 1\n"
    opened.clear()
    assert library.read_small("q.robot") == library.read("q.robot") == "program Q\nwait 1\n"
    assert opened == []
