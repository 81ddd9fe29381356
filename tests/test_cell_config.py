"""The cell configuration: the shipped cells, every error it reports, and `uacell config check`."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path
from typing import cast

import pytest

from uacell.binding.cell import Part, demo_cell
from uacell.config import load_cell, load_config
from uacell.core.cell_file import STATE_MACHINE, builtin_cell_path
from uacell.core.errors import ConfigError
from uacell.packml.config import UnitsSection
from uacell.robotics.config import RobotsSection
from uacell.robotics.equipment import ExecutionMode, StopMode


def _demo_before_configuration() -> list[tuple[str, Part]]:
    """The demo cell as uacell hard-coded it before cells were configured (frozen here)."""
    axes = [
        Part(
            f"Axis{i}",
            "Robotics",
            "AxisType",
            "Axes",
            include=("ParameterSet/ActualSpeed", "ParameterSet/ActualAcceleration"),
        )
        for i in range(1, 7)
    ]
    power_trains = [
        Part(
            f"PowerTrain{i}",
            "Robotics",
            "PowerTrainType",
            "PowerTrains",
            children=[Part(f"Motor{i}", "Robotics", "MotorType")],
        )
        for i in range(1, 7)
    ]
    arm = Part(
        "Arm1",
        "Robotics",
        "MotionDeviceType",
        "MotionDevices",
        include=("ParameterSet/InControl", "ParameterSet/OnPath", "FlangeLoad"),
        children=axes + power_trains,
        role="motion_device",
    )
    task_control = Part(
        "TaskControl1",
        "Robotics",
        "TaskControlType",
        "TaskControls",
        include=(
            "Lock",
            "ParameterSet/ExecutionMode",
            "TaskModules",
            "TaskControlOperation",
            "TaskControlOperation/**",
            *STATE_MACHINE,
        ),
        role="task_control",
    )
    controller = Part(
        "Controller1",
        "Robotics",
        "ControllerType",
        "Controllers",
        include=("Lock", "Programs", "SystemOperation", "SystemOperation/**", *STATE_MACHINE),
        children=[task_control, Part("Software1", "DI", "SoftwareType", "Software")],
        role="controller",
    )
    robot = Part(
        "Robot1",
        "Robotics",
        "MotionDeviceSystemType",
        children=[controller, arm, Part("SafetyState1", "Robotics", "SafetyStateType", "SafetyStates")],
        role="robot",  # since Machinery: its DataSet names the robot (docs/machinery.md)
    )
    filler = Part("Filler1", "PackML", "PackMLBaseObjectType", include=("**",), role="packml_unit")
    return [("DeviceSet", robot), ("PackMLObjects", filler)]


def test_the_default_cell_is_the_shipped_demo_and_has_the_shape_of_the_old_demo():
    assert demo_cell() == _demo_before_configuration()
    assert load_config().cell.parts() == _demo_before_configuration()
    assert load_config().cell.source == str(builtin_cell_path("demo"))


def test_a_configuration_without_a_cell_serves_the_demo(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[server]\nport = 4900\n")
    assert load_config(path).cell.parts() == _demo_before_configuration()


def test_the_example_is_the_larger_cell_the_docs_describe():
    cell = load_cell(builtin_cell_path("example"))
    robots = cast(RobotsSection, cell.sections["robots"]).robots
    assert [r.name for r in robots] == ["Welder", "Handler"]
    welder = robots[0]
    assert [(c.name, [t.name for t in c.task_controls], c.motion_device) for c in welder.controllers] == [
        ("ControllerA", ["Seam", "Service"], "ArmA"),
        ("ControllerB", ["Seam", "Cleaning"], "ArmB"),
    ]
    assert [len(m.axes) for m in welder.motion_devices] == [6, 7]
    a = welder.controllers[0]
    assert a.possible_stop_modes == (StopMode.ON_PATH, StopMode.QUICK_STOP, StopMode.END_OF_CYCLE)
    assert a.default_stop_mode is StopMode.QUICK_STOP
    assert a.task_controls[1].execution_mode is ExecutionMode.STEP
    units = cast(UnitsSection, cell.sections["packml_units"]).units
    assert [(u.name, u.mach_speed, u.design_speed) for u in units] == [
        ("Filler", 60.0, 120.0),
        ("Capper", 180.0, 300.0),
        ("Labeler", 600.0, 900.0),
    ]
    assert units[2].unit_mode == 2  # Maintenance


MINIMAL = """
[[robots]]
name = "R"
"""


def test_a_robot_table_alone_gets_one_controller_task_control_and_six_axis_arm(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(MINIMAL)
    robot = cast(RobotsSection, load_cell(path).sections["robots"]).robots[0]
    assert [c.name for c in robot.controllers] == ["Controller1"]
    assert [t.name for t in robot.controllers[0].task_controls] == ["TaskControl1"]
    assert [(m.name, len(m.axes)) for m in robot.motion_devices] == [("Arm1", 6)]
    assert robot.controllers[0].motion_device == "Arm1"


BASE = """
[[robots]]
name = "R"
  [[robots.controllers]]
  name = "C1"
    [[robots.controllers.task_controls]]
    name = "T1"
  [[robots.motion_devices]]
  name = "Arm"
  axes = 6
[[packml_units]]
name = "U"
"""

# (what to change in BASE, the one line expected after "configuration FILE: ")
ERRORS = [
    (('[[robots]]\nname = "R"\n', '[[robots]]\nname = "R"\ncolour = "red"\n'), "[robots.R] colour: unknown key"),
    (('name = "T1"', 'name = "T1"\n    speed = 3'), "[robots.R.controllers.C1.task_controls.T1] speed: unknown key"),
    (
        ('name = "Arm"', 'name = "Arm"\n  identification = { colour = "x" }'),
        "[robots.R.motion_devices.Arm.identification] colour: unknown key",
    ),
    (
        ('name = "T1"', 'name = "T1"\n    [[robots.controllers.task_controls]]\n    name = "T1"'),
        "[robots.R.controllers.C1.task_controls.T1] name: a task control named 'T1' is declared twice",
    ),
    (
        ('name = "U"', 'name = "R"'),
        "[packml_units.R] name: 'R' is declared twice: the [[robots]] entry [robots.R] has that name already",
    ),
    (
        ('name = "U"', 'name = "U"\n[[packml_units]]\nname = "U"'),
        "[packml_units.U] name: 'U' is declared twice: the [[packml_units]] entry [packml_units.U] has that name",
    ),
    (('name = "Arm"', 'name = "Arm.1"'), "[robots.R.motion_devices[1]] name: 'Arm.1' cannot be a BrowseName here"),
    (('name = "C1"', 'name = "C 1"'), "[robots.R.controllers[1]] name: 'C 1' cannot be a BrowseName here"),
    (('name = "U"', 'name = ""'), "[packml_units[1]] name: '' cannot be a BrowseName here"),
    (('name = "U"', 'name = "1U"'), "[packml_units[1]] name: '1U' cannot be a BrowseName here"),
    (('name = "U"', 'title = "U"'), "[packml_units[1]] name: is missing (every part needs a name)"),
    (('name = "U"', 'nam = "U"'), "[packml_units[1]] name: is missing (every part needs a name); is 'nam' meant"),
    (("axes = 6", "axes = 0"), "[robots.R.motion_devices.Arm] axes: a motion device needs at least one axis"),
    (("axes = 6", "axes = []"), "[robots.R.motion_devices.Arm] axes: a motion device needs at least one axis"),
    (("axes = 6", 'axes = ["J1", "J1"]'), "[robots.R.motion_devices.Arm] axes: an axis named 'J1' is declared twice"),
    (
        ("axes = 6", 'axes = [{ name = "J1", min_position = 10.0, max_position = -10.0 }]'),
        "[robots.R.motion_devices.Arm.axes.J1] max_position: must be greater than min_position",
    ),
    (
        ('name = "C1"', 'name = "C1"\n  default_stop_mode = "Brake"'),
        "[robots.R.controllers.C1] default_stop_mode: 'Brake' is not one of OnPath, EndOfCycle",
    ),
    (
        ('name = "C1"', 'name = "C1"\n  possible_stop_modes = ["OnPath", "Halt"]'),
        "[robots.R.controllers.C1] possible_stop_modes: 'Halt' is not one of OnPath",
    ),
    (
        ('name = "C1"', 'name = "C1"\n  possible_stop_modes = ["QuickStop"]\n  default_stop_mode = "OnPath"'),
        "[robots.R.controllers.C1] default_stop_mode: 'OnPath' is not in possible_stop_modes",
    ),
    (
        ('name = "T1"', 'name = "T1"\n    execution_mode = "FAST"'),
        "[robots.R.controllers.C1.task_controls.T1] execution_mode: 'FAST' is not one of CYCLE, CONTINUOUS, STEP",
    ),
    (
        ('name = "C1"', 'name = "C1"\n  motion_device = "Arm9"'),
        "[robots.R.controllers.C1] motion_device: 'Arm9' is not a motion device of this robot",
    ),
    (('name = "C1"', 'name = "C1"\n  time_scale = 0'), "[robots.R.controllers.C1] time_scale: must be greater than 0"),
    (
        ('name = "U"', 'name = "U"\nunit_mode = "Sleep"'),
        "[packml_units.U] unit_mode: 'Sleep' is not one of Produce, Maintenance, Manual",
    ),
    (
        ('name = "U"', 'name = "U"\nmach_speed = 900.0'),
        "[packml_units.U] mach_speed: 900 is outside mach_speed_range 0..600",
    ),
    (
        ('name = "U"', 'name = "U"\nmach_speed_range = [50.0, 10.0]'),
        "[packml_units.U] mach_speed_range: must satisfy 0 <= minimum < maximum",
    ),
    (
        ('name = "U"', 'name = "U"\nacting_times = { Sleeping = 1.0 }'),
        "[packml_units.U.acting_times] Sleeping: unknown key",
    ),
    (('name = "U"', 'name = "U"\nsettings = 3'), "[packml_units.U] settings: must be a table"),
    (
        ('name = "U"', 'name = "U"\nequipment = 3'),
        "[packml_units.U] equipment: must be 'package.module:factory' or a table with a driver",
    ),
    (
        ('name = "U"', 'name = "U"\nequipment = { host = "x" }'),
        "[packml_units.U] equipment: needs a driver (logix-packtags, modbus-packtags, opcua-packtags, s7-packtags)",
    ),
    (
        ('name = "U"', 'name = "U"\nequipment = { driver = "modbus-signals", host = "a" }'),
        "[packml_units.U] equipment: driver 'modbus-signals' is not one of: "
        "logix-packtags, modbus-packtags, opcua-packtags, s7-packtags",
    ),
    (
        ("[[packml_units]]", '[server]\nanonymous_role = "guest"\n[[packml_units]]'),
        "[server] anonymous_role: must be one of observer, operator, engineer, admin",
    ),
    (("[[packml_units]]", "[cell]\n[[packml_units]]"), "[cell]: unknown section"),
    (("[[packml_units]]", "[serve]\n[[packml_units]]"), "[serve]: unknown section; did you mean 'server'?"),
    (("[[packml_units]]", "[server]\nprot = 1\n[[packml_units]]"), "[server] prot: unknown key; did you mean 'port'?"),
    (("[[packml_units]]", "[server]\nport = 'x'\n[[packml_units]]"), "[server] port: must be an integer"),
    (("[[packml_units]]", "[robot]\nmotion_devices = 1\n[[packml_units]]"), "[robot] motion_devices: unknown key"),
    (
        ('name = "U"', 'name = "U"\nmach_speed_ragne = [0.0, 10.0]'),
        "[packml_units.U] mach_speed_ragne: unknown key; did you mean 'mach_speed_range'?",
    ),
    (
        ('name = "U"', 'name = "Füller"'),
        "[packml_units[1]] name: 'Füller' cannot be a BrowseName here: use an ASCII letter or '_' followed by up to 63"
        " ASCII letters, digits, '_' or '-' ('ü' is not ASCII)",
    ),
    (
        ("axes = 6", 'axes = ["J1", "J 2"]'),
        "[robots.R.motion_devices.Arm] axes[2]: 'J 2' cannot be a BrowseName here",
    ),
    (
        ("[[packml_units]]", '[server]\napplication_uri = ""\n[[packml_units]]'),
        "[server] application_uri: must not be empty",
    ),
]


@pytest.mark.parametrize(("change", "message"), ERRORS, ids=[e[1][:48] for e in ERRORS])
def test_every_configuration_error_is_one_line_naming_file_table_and_key(tmp_path, change, message):
    path = tmp_path / "cell.toml"
    old, new = change
    assert old in BASE or old in MINIMAL
    path.write_text(BASE.replace(old, new, 1))
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert "\n" not in text
    assert text.startswith(f"configuration {path}: {message}"), text


def test_two_controllers_of_one_robot_may_not_move_the_same_arm(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text(
        BASE.replace(
            'name = "C1"',
            'name = "C0"\n  motion_device = "Arm"\n  [[robots.controllers]]\n  name = "C1"\n  motion_device = "Arm"',
        )
    )
    with pytest.raises(
        ConfigError, match=r": \[robots.R\] controllers: motion device 'Arm' is controlled by two controllers$"
    ):
        load_config(path)


def test_the_same_name_in_different_places_is_fine(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text(
        textwrap.dedent("""
        [[robots]]
        name = "A"
          [[robots.controllers]]
          name = "C"
            [[robots.controllers.task_controls]]
            name = "T"
        [[robots]]
        name = "B"
          [[robots.controllers]]
          name = "C"
            [[robots.controllers.task_controls]]
            name = "T"
    """)
    )
    cell = load_cell(path)
    assert [p.name for _, p in cell.parts()] == ["A", "B"]


def _uacell(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "uacell", *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_config_check_prints_the_tree_it_would_serve_without_serving(tmp_path):
    proc = _uacell("config", "check", str(builtin_cell_path("example")))
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    assert out[-1] == "configuration OK"
    assert "endpoint: opc.tcp://127.0.0.1:4840/" in out
    assert "anonymous clients: operator; SecurityPolicy None offered" in out
    assert "application: uacell example cell (urn:" in "\n".join(out)
    assert "    Controllers/ControllerB  ControllerType  equipment: simulator (time_scale 2)" in out
    assert "      TaskControls/Cleaning  TaskControlType  ExecutionMode CONTINUOUS" in out
    assert "    MotionDevices/ArmB  MotionDeviceType  7 axes: J1 J2 J3 J4 J5 J6 J7" in out
    assert any(line.startswith("  PackMLObjects/Labeler  PackMLBaseObjectType") for line in out)


def test_config_check_prints_the_values_in_effect_where_a_part_takes_a_section_default(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[robot]\ntime_scale = 4.0\n[packml]\nacting_time = 0.5\nmach_speed = 30.0\n")
    proc = _uacell("config", "check", str(path))
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    assert "    Controllers/Controller1  ControllerType  equipment: simulator (time_scale 4 from [robot])" in out
    assert (
        "  PackMLObjects/Filler1  PackMLBaseObjectType  equipment: simulator (acting states 0.5 s from [packml])" in out
    )
    assert "      MachSpeed 30 (from [packml]) in 0..600, design 120 packages/min; unit mode Produce" in out
    path.write_text('[packml]\nequipment = "uacell.packml.sim:simulator"\n')
    proc = _uacell("config", "check", str(path))
    assert "equipment: uacell.packml.sim:simulator (from [packml] equipment)" in proc.stdout, proc.stderr


def test_config_check_without_a_file_shows_the_demo_and_names_a_remote_listening_policy(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[server]\nhost = "0.0.0.0"\n')
    proc = _uacell("config", "check", str(path))
    assert proc.returncode == 0, proc.stderr
    assert "anonymous clients: observer; SecurityPolicy None not offered" in proc.stdout
    assert "  DeviceSet/Robot1  MotionDeviceSystemType" in proc.stdout.splitlines()


def test_config_check_and_serve_exit_2_with_one_line_on_an_error(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text(BASE.replace("axes = 6", "axes = 0"))
    expected = (
        f"uacell: configuration {path}: [robots.R.motion_devices.Arm] axes: a motion device needs at least one axis"
    )
    for args in (("config", "check", str(path)), ("serve", "--config", str(path), "--data-dir", str(tmp_path / "d"))):
        proc = _uacell(*args)
        assert proc.returncode == 2
        assert proc.stderr.strip().splitlines() == [expected]
        assert proc.stdout == ""
    assert not (tmp_path / "d").exists()  # nothing was started


def test_config_check_names_an_equipment_factory_that_cannot_be_loaded(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text(BASE.replace('name = "U"', 'name = "U"\nequipment = "surely_missing_module_x:make"'))
    proc = _uacell("config", "check", str(path))
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f"uacell: configuration {path}: [packml_units.U] equipment: 'surely_missing_module_x:make' cannot be loaded:"
        " No module named 'surely_missing_module_x'"
    )
    path.write_text(BASE.replace('name = "C1"', 'name = "C1"\n  equipment = "surely_missing_module_x:make"'))
    proc = _uacell("config", "check", str(path))
    assert proc.stderr.strip().startswith(
        f"uacell: configuration {path}: [robots.R.controllers.C1] equipment: 'surely_missing_module_x:make' cannot"
    )


def test_the_application_uri_is_per_host_unless_configured(tmp_path):
    import socket

    config = load_config()
    assert config.server.application_uri.startswith("urn:") and config.server.application_uri != "urn:uacell:server"
    assert socket.gethostname().split(".")[0] in config.server.application_uri
    path = tmp_path / "c.toml"
    path.write_text('[server]\napplication_uri = "urn:plant7:line3:uacell"\napplication_name = "Line 3 cell"\n')
    config = load_config(path)
    assert (config.server.application_uri, config.server.application_name) == ("urn:plant7:line3:uacell", "Line 3 cell")


def test_builtin_cells_exist():
    for name in ("demo", "example"):
        assert Path(builtin_cell_path(name)).is_file()
