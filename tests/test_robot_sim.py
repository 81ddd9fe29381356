"""The simulated robot: axes, motion within limits, power, execution modes, each stop mode, alarms."""

from __future__ import annotations

import asyncio

import pytest
from helpers import VirtualTime, wait_until

from uacell.robotics.equipment import (
    AlarmStop,
    EquipmentError,
    ExecutionMode,
    NotPowered,
    RobotEquipment,
    RunOutcome,
    StopMode,
)
from uacell.robotics.program import parse
from uacell.robotics.sim import BRAKE_TIME, DEFAULT_AXES, SimulatedRobot

SCALE = 0.01  # 1 simulated second = 10 ms
TASK = "T1"
# Axis 6 is slowest to cover 700 degrees at 10 %: 700 / 60 = 11.7 simulated s (117 ms).
LONG = """\
program Long
speed 10
move 0 0 0 0 0 -350
move 0 0 0 0 0 350
move 0 0 0 0 0 0
"""
GROUPED = """\
program Grouped
use M
speed 10
move 0 0 0 0 0 -350
call M.two
move 0 0 0 0 0 0
"""
MODULE = """\
module M
routine two
  speed 10
  move 0 0 0 0 0 350
  move 0 0 0 0 0 300
end
"""


async def powered_robot(*texts: str, scale: float = SCALE) -> SimulatedRobot:
    robot = SimulatedRobot(time_scale=scale, power_up_time=0.1)
    await robot.power_up()
    for text in texts:
        await robot.load(TASK, parse(text, [a.limits for a in robot.axes]))
    return robot


class Recorder:
    def __init__(self) -> None:
        self.pointers: list[int] = []
        self.lines: list[int] = []

    def __call__(self, pointer: int, line: int) -> None:
        self.pointers.append(pointer)
        self.lines.append(line)


def test_implements_the_protocol_with_a_realistic_arm() -> None:
    robot = SimulatedRobot()
    assert isinstance(robot, RobotEquipment)
    assert [a.name for a in robot.axes] == ["A1", "A2", "A3", "A4", "A5", "A6"]
    for axis in robot.axes:
        assert axis.min_position < 0 < axis.max_position and 100 <= axis.max_speed <= 1000
    assert [(s.position, s.speed) for s in robot.axis_states()] == [(0.0, 0.0)] * 6
    assert robot.alarm_names == ("EmergencyStop", "CollisionDetected")


async def test_power_takes_time_and_run_needs_power() -> None:
    robot = SimulatedRobot(time_scale=SCALE, power_up_time=2.0)
    await robot.load(TASK, parse(LONG))
    with pytest.raises(NotPowered):
        await robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder())
    t0 = asyncio.get_running_loop().time()
    await robot.power_up()
    assert robot.powered and asyncio.get_running_loop().time() - t0 >= 2.0 * SCALE * 0.9
    await robot.power_down()
    assert not robot.powered
    robot.fail_power_up = True
    with pytest.raises(EquipmentError):
        await robot.power_up()
    assert not robot.powered


async def test_motion_reaches_targets_within_limits_and_speeds() -> None:
    robot = await powered_robot("program P\nspeed 50\nmove 90 -50 40 100 -60 200\nmove -90 100 -150 0 60 -300\n")
    progress = Recorder()
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, progress))
    samples = []
    while not run.done():
        samples.append(robot.axis_states())
        await asyncio.sleep(0.001)
    assert await run == RunOutcome(0, True)
    assert progress.pointers == [0, 1] and progress.lines == [3, 4]
    moving = [s for s in samples if any(a.speed for a in s)]
    assert len(moving) > 5
    for states in samples:
        for axis, state in zip(DEFAULT_AXES, states, strict=True):
            assert axis.min_position - 1e-6 <= state.position <= axis.max_position + 1e-6
            assert abs(state.speed) <= axis.max_speed * 0.5 + 1e-6
    # The slowest axis of a synchronized move runs at its full overridden speed.
    assert any(abs(s[5].speed) == pytest.approx(DEFAULT_AXES[5].max_speed * 0.5) for s in moving)
    assert robot.positions == (-90.0, 100.0, -150.0, 0.0, 60.0, -300.0)
    assert all(a.speed == 0.0 for a in robot.axis_states())


async def test_step_mode_executes_one_instruction_per_run() -> None:
    robot = await powered_robot("program P\nmove 10 0 0 0 0 0\nwait 0.1\nmove 20 0 0 0 0 0\n")
    outcomes = [await robot.run(TASK, p, ExecutionMode.STEP, Recorder()) for p in (0, 1, 2)]
    assert outcomes == [RunOutcome(1, False), RunOutcome(2, False), RunOutcome(0, True)]
    assert robot.positions[0] == 20.0


async def test_continuous_mode_restarts_until_stopped() -> None:
    robot = await powered_robot("program P\nmove 10 0 0 0 0 0\nmove 0 0 0 0 0 0\n", scale=0.001)
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CONTINUOUS, Recorder()))
    await wait_until(lambda: robot.cycles >= 3)
    await robot.stop(TASK, StopMode.END_OF_CYCLE)
    assert await run == RunOutcome(0, True)
    assert robot.positions == (0.0,) * 6


async def start_long(
    text: str = LONG, *more: str, scale: float = SCALE
) -> tuple[SimulatedRobot, asyncio.Task[RunOutcome]]:
    robot = await powered_robot(*more, text, scale=scale)
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder()))
    await wait_until(lambda: robot.positions[5] < -30)  # well inside the first move
    return robot, run


async def test_quick_stop_stops_at_once() -> None:
    robot, run = await start_long()
    await robot.stop(TASK, StopMode.QUICK_STOP)
    at_request = robot.positions[5]
    outcome = await asyncio.wait_for(run, 2.0)
    assert outcome == RunOutcome(0, False)  # the cut move is redone on resume
    assert robot.positions[5] == pytest.approx(at_request, abs=1.0)  # no further than a tick
    assert -350 < robot.positions[5] < 0 and not robot.moving


async def test_on_path_brakes_along_the_path() -> None:
    # A slower clock, so that event-loop latency is small against the braking distance.
    scale = 0.1
    robot, run = await start_long(scale=scale)
    loop = asyncio.get_running_loop()
    speed = robot.axis_states()[5].speed
    at_request, requested = robot.positions[5], loop.time()
    await robot.stop(TASK, StopMode.ON_PATH)
    await wait_until(lambda: robot.axis_states()[5].speed != speed or run.done())
    # The run sees the stop at its next step: on a loaded machine that can be a few milliseconds
    # later, and the axis goes on at ``speed`` until then (never faster).
    late = abs(speed) * (loop.time() - requested) / scale
    assert run.done() or abs(robot.axis_states()[5].speed) < abs(speed)  # decelerating
    outcome = await run
    assert outcome == RunOutcome(0, False)
    braked = at_request - robot.positions[5]
    assert 0 < braked <= abs(speed) * BRAKE_TIME / 2 + late + 2.0  # along the path, within braking distance
    assert not robot.moving


async def test_end_of_instruction_finishes_the_move() -> None:
    robot, run = await start_long()
    await robot.stop(TASK, StopMode.END_OF_INSTRUCTION)
    assert await run == RunOutcome(1, False)
    assert robot.positions[5] == -350.0


async def test_end_of_cycle_finishes_the_program() -> None:
    robot, run = await start_long()
    await robot.stop(TASK, StopMode.END_OF_CYCLE)
    assert await run == RunOutcome(0, True)
    assert robot.positions[5] == 0.0


async def test_process_stop_outside_a_routine_is_end_of_instruction() -> None:
    robot, run = await start_long(GROUPED, MODULE)
    await robot.stop(TASK, StopMode.PROCESS_STOP)
    assert await run == RunOutcome(1, False)
    assert robot.positions[5] == -350.0


async def test_process_stop_finishes_the_routine_call() -> None:
    robot = await powered_robot(MODULE, GROUPED)
    progress = Recorder()
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, progress))
    await wait_until(lambda: progress.pointers[-1:] == [1] and robot.positions[5] > -300)  # inside M.two
    await robot.stop(TASK, StopMode.PROCESS_STOP)
    assert await run == RunOutcome(3, False)  # both moves of the routine done, the last one not
    assert robot.positions[5] == 300.0


async def test_wait_is_cut_by_quick_stop_and_finished_by_end_of_instruction() -> None:
    robot = await powered_robot("program W\nwait 5\nwait 5\n")
    progress = Recorder()
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, progress))
    await wait_until(lambda: progress.pointers == [0])  # inside the first wait
    await robot.stop(TASK, StopMode.QUICK_STOP)
    assert await asyncio.wait_for(run, 1.0) == RunOutcome(0, False)  # not the 2 x 50 ms of waits
    progress = Recorder()
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, progress))
    await wait_until(lambda: progress.pointers == [0])
    t0 = asyncio.get_running_loop().time()
    await robot.stop(TASK, StopMode.END_OF_INSTRUCTION)
    assert await run == RunOutcome(1, False)
    assert asyncio.get_running_loop().time() - t0 > 0.02  # the rest of the 50 ms wait


async def test_alarm_stops_the_run_and_is_reported() -> None:
    robot, run = await start_long()
    seen: list[tuple[str, bool, str]] = []
    robot.add_alarm_listener(lambda *a: seen.append(a))
    robot.raise_alarm("CollisionDetected", "axis 6 torque")
    with pytest.raises(AlarmStop, match="CollisionDetected"):
        await asyncio.wait_for(run, 2.0)
    assert not robot.moving
    with pytest.raises(EquipmentError):
        await robot.power_up()  # an active alarm keeps the drives off
    robot.clear_alarm("CollisionDetected")
    assert seen == [("CollisionDetected", True, "axis 6 torque"), ("CollisionDetected", False, "axis 6 torque")]
    with pytest.raises(KeyError):
        robot.raise_alarm("NoSuchAlarm")


async def test_alarm_raised_before_the_run_begins_stops_it() -> None:
    robot = await powered_robot(LONG)
    robot.raise_alarm("EmergencyStop")  # e.g. between a Start and the run's first instruction
    with pytest.raises(AlarmStop, match="EmergencyStop"):
        await robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder())
    assert not robot.moving and robot.positions == (0.0,) * 6


async def test_load_unload_and_refusals() -> None:
    robot = await powered_robot(LONG)
    with pytest.raises(EquipmentError, match="not loaded"):
        await robot.unload(TASK, "Other")
    run = asyncio.create_task(robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder()))
    await asyncio.sleep(0)
    with pytest.raises(EquipmentError, match="running"):
        await robot.load(TASK, parse("program X\nwait 0\n"))
    await robot.stop(TASK, StopMode.QUICK_STOP)
    await run
    await robot.unload(TASK, "Long")
    with pytest.raises(EquipmentError, match="no program"):
        await robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder())
    await robot.load(TASK, parse(GROUPED))
    with pytest.raises(EquipmentError, match="module M is not loaded"):
        await robot.run(TASK, 0, ExecutionMode.CYCLE, Recorder())


async def test_an_injected_clock_runs_hours_of_robot_time_without_wall_time() -> None:
    """Model tests need not depend on wall time: the simulator takes its clock and sleep."""
    time = VirtualTime(1000.0)
    robot = SimulatedRobot(power_up_time=3600.0, clock=time.clock, sleep=time.sleep)
    loop = asyncio.get_running_loop()
    started = loop.time()
    await robot.power_up()
    assert robot.powered and time.now == pytest.approx(1000.0 + 3600.0)
    text = "program P\nspeed 1\nmove 0 0 0 0 0 -350\nwait 3600\nmove 0 0 0 0 0 0\n"
    await robot.load(TASK, parse(text, [a.limits for a in robot.axes]))
    progress = Recorder()
    outcome = await robot.run(TASK, 0, ExecutionMode.CYCLE, progress)
    assert outcome == RunOutcome(0, True) and progress.pointers == [0, 1, 2]
    assert robot.positions[5] == 0.0
    # 350 degrees at 1 % of axis 6's speed, there and back, plus the one-hour wait.
    move = 350.0 / (DEFAULT_AXES[5].max_speed * 0.01)
    assert time.slept == pytest.approx(3600.0 + 2 * move + 3600.0, rel=1e-6)
    assert loop.time() - started < 5.0  # hours of robot time, no wall time to speak of
