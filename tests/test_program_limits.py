"""Issue-12 finding 1: a program cannot stall the server. Limits on size, lines, nesting, steps, call
depth and work; loading and starting stay off the event loop; a running program yields between steps."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import robotics_tables

from uacell.robotics.equipment import ExecutionMode, StopMode
from uacell.robotics.loading import INLINE_PROGRAM_BYTES, LoadFailure, ProgramLoading
from uacell.robotics.model import RobotCell, Status
from uacell.robotics.program import (
    NothingToExecute,
    ProgramError,
    ProgramLimits,
    ProgramTooLarge,
    expand,
    measure,
    parse,
)
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot

SPIN3 = "program Spin3\nrepeat 10000\nrepeat 10000\nrepeat 10000\nspeed 50\nend\nend\nend\n"
SPIN3_WAIT = SPIN3.replace("speed 50", "wait 0")
TOOL = "module Tool\nroutine empty\n  speed 10\nend\nroutine one\n  wait 0\nend\n"


def deep(levels: int) -> str:
    return "program Deep\n" + "repeat 2\n" * levels + "wait 0\n" + "end\n" * levels


def timed(fn, *args):
    start = time.perf_counter()
    try:
        return fn(*args), time.perf_counter() - start
    except ProgramError as e:
        return e, time.perf_counter() - start


# --- pure: the format's limits -----------------------------------------------------------------------
def test_loops_around_nothing_are_refused_at_once() -> None:
    spin = parse(SPIN3)
    error, seconds = timed(expand, spin, {})
    assert isinstance(error, NothingToExecute)
    assert seconds < 1.0
    with pytest.raises(NothingToExecute):
        measure(spin, {})


def test_loops_beyond_max_steps_are_refused_without_unrolling() -> None:
    spin = parse(SPIN3_WAIT)
    error, seconds = timed(expand, spin, {})
    assert isinstance(error, ProgramTooLarge) and "more than 20000 steps" in error.reason
    assert seconds < 1.0


def test_nesting_depth_is_limited_at_parse() -> None:
    with pytest.raises(ProgramTooLarge) as info:
        parse(deep(4000))
    assert info.value.line == 18 and "nest deeper than 16" in info.value.reason
    assert len(expand(parse(deep(10)), {})) == 2**10
    with pytest.raises(ProgramTooLarge):
        parse(deep(4), bounds=ProgramLimits(max_nesting=3))


def test_file_size_and_line_count_are_limited() -> None:
    text = "program Big\n" + "wait 0\n" * 100
    with pytest.raises(ProgramTooLarge, match="larger than 500 bytes"):
        parse(text, bounds=ProgramLimits(max_file_bytes=500))
    with pytest.raises(ProgramTooLarge, match="more than 50 lines"):
        parse(text, bounds=ProgramLimits(max_lines=50))
    assert len(parse(text, bounds=ProgramLimits(max_lines=101)).instructions) == 100


def test_steps_call_depth_and_work_are_configurable() -> None:
    text = "program P\nrepeat 100\nwait 0\nend\n"
    with pytest.raises(ProgramTooLarge, match="more than 99 steps"):
        expand(parse(text), {}, ProgramLimits(max_steps=99))
    assert len(expand(parse(text), {}, ProgramLimits(max_steps=100))) == 100
    chain = "module C\n" + "".join(f"routine r{i}\n  call C.r{i + 1}\nend\n" for i in range(5))
    chain += "routine r5\n  wait 0\nend\n"
    program = parse("program P\nuse C\ncall C.r0\n")
    assert len(expand(program, {"C": parse(chain)}, ProgramLimits(max_call_depth=6))) == 1
    with pytest.raises(ProgramError, match="nest deeper than 5"):
        expand(program, {"C": parse(chain)}, ProgramLimits(max_call_depth=5))
    # Many instructions that do not become steps still cost work: the budget stops them.
    busy = "program Busy\nrepeat 10000\nwait 0\n" + "speed 50\n" * 30 + "end\n"
    error, seconds = timed(expand, parse(busy), {})
    assert isinstance(error, ProgramTooLarge) and "instructions to expand" in error.reason
    assert seconds < 2.0


def test_bodies_without_steps_keep_their_speed_effect() -> None:
    text = "program P\nuse Tool\nrepeat 10000\nrepeat 10000\nspeed 30\nend\nend\ncall Tool.empty\nmove 0 0 0 0 0 0\n"
    program = parse(text)
    steps = expand(program, {"Tool": parse(TOOL)})
    assert [(s.kind, s.speed, s.group) for s in steps] == [("move", 30.0, None)]


def test_measure_counts_without_building_and_partial_skips_unknown_modules() -> None:
    program = parse("program P\nuse Tool\nrepeat 3\ncall Tool.one\nwait 1\nend\n")
    tool = parse(TOOL)
    assert measure(program, {"Tool": tool}) == len(expand(program, {"Tool": tool})) == 6
    assert measure(program, {}, partial=True) == 3
    with pytest.raises(ProgramError, match="not loaded"):
        measure(program, {})
    assert measure(parse("program Q\nuse Tool\ncall Tool.one\n"), {}, partial=True) == 0  # no error: unknown


def test_limits_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_steps"):
        ProgramLimits(max_steps=0)


# --- model: loading refuses with -2, off the event loop -----------------------------------------------
async def _loop_lag_during(coro, interval: float = 0.005):
    """Run ``coro`` while measuring the longest gap between ticks of a ticker task."""
    loop = asyncio.get_running_loop()
    worst = 0.0
    done = False

    async def tick() -> None:
        nonlocal worst
        last = loop.time()
        while not done:
            await asyncio.sleep(interval)
            now = loop.time()
            worst = max(worst, now - last - interval)
            last = now

    ticker = asyncio.create_task(tick())
    try:
        result = await coro
    finally:
        done = True
        await ticker
    return result, worst


@contextlib.contextmanager
def _checks_recorded() -> Iterator[list[bool]]:
    """For each time a load read and checked a program file: whether that ran on the event loop's
    thread (the timing of a shared machine says nothing reliable about it; the thread does)."""
    loop_thread = threading.get_ident()
    ran: list[bool] = []
    original = ProgramLoading._read_and_check

    def recorded(self: ProgramLoading, *args: Any, **kwargs: Any) -> Any:
        try:
            result = original(self, *args, **kwargs)
        except LoadFailure:
            ran.append(threading.get_ident() == loop_thread)
            raise
        if result is not None:  # None: too large to be read on the loop, not read
            ran.append(threading.get_ident() == loop_thread)
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ProgramLoading, "_read_and_check", recorded)
        yield ran


@pytest.fixture
async def cell(tmp_path: Path):
    files = {
        "spin3.robot": SPIN3,
        "spin3wait.robot": SPIN3_WAIT,
        "deep.robot": deep(4000),
        "busy.robot": "program Busy\n" + "wait 0\n" * 9000,
        "latin1.robot": "program Caf\xe9\nwait 0\n",
        "spin.robot": "program Spin\nwait 0\n",
        "tool.robot": "module Tool\nroutine big\n  repeat 10000\n    wait 0\n  end\nend\n",
        "usesbig.robot": "program UsesBig\nuse Tool\nrepeat 3\ncall Tool.big\nend\n",
        "huge.robot": "program Huge\n" + "# padding\n" * 20000,
    }
    for name, text in files.items():
        data = text.encode("latin-1") if name == "latin1.robot" else text.encode()
        (tmp_path / name).write_bytes(data)
    robot = SimulatedRobot(time_scale=0.0005, power_up_time=2.0, power_down_time=0.5)
    c = RobotCell(robot, DirectoryLibrary(tmp_path), tables=robotics_tables())
    yield c
    await c.close()


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        ("spin3", "no move or wait"),
        ("spin3wait", "more than 20000 steps"),
        ("deep", "nest deeper than 16"),
        ("huge", "larger than 131072 bytes"),
        ("latin1", "not UTF-8 text"),
    ],
)
async def test_load_beyond_the_limits_answers_invalid_content_quickly(
    cell: RobotCell, name: str, reason: str, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    tc = cell.tasks["TaskControl1"]
    with _checks_recorded() as checked:
        status = await tc.load_by_name(name)
    assert status == Status.INVALID_CONTENT
    assert reason in tc.last_error
    assert any(reason in r.getMessage() for r in caplog.records)
    assert tc.state == "Idle" and not tc.program_loaded
    # A file of more than INLINE_PROGRAM_BYTES is read and checked in a worker thread; a smaller one
    # on the loop, its checks bounded by the limits (the refusal says which bound stopped them).
    inline = (tmp_path / f"{name}.robot").stat().st_size <= INLINE_PROGRAM_BYTES
    assert checked == [inline]


async def test_a_large_valid_program_loads_without_stalling_the_loop(cell: RobotCell, tmp_path: Path) -> None:
    tc = cell.tasks["TaskControl1"]
    assert (tmp_path / "busy.robot").stat().st_size > INLINE_PROGRAM_BYTES
    with _checks_recorded() as checked:
        status = await tc.load_by_name("busy")
    assert status == Status.OK and tc.program_name == "Busy"
    assert checked == [False]  # read, parsed and measured in a worker thread, not on the event loop


async def test_start_refuses_a_program_that_only_exceeds_the_limits_with_its_modules(cell: RobotCell) -> None:
    tc = cell.tasks["TaskControl1"]
    assert await cell.system.get_ready() == Status.OK
    while cell.system.state != "Ready":
        await asyncio.sleep(0.001)
    assert await tc.load_by_name("usesbig") == Status.OK  # Tool not loaded: unknown yet
    assert await tc.load_by_name("tool") == Status.OK
    assert not tc.executable("TaskControlStateMachine", "Start")
    assert await tc.start() == Status.INVALID_CONTENT
    assert "more than 20000 steps" in tc.last_error
    assert tc.state == "Ready"


async def test_a_running_program_of_instant_steps_yields_to_the_loop(cell: RobotCell) -> None:
    tc = cell.tasks["TaskControl1"]
    assert await cell.system.get_ready() == Status.OK
    while cell.system.state != "Ready":
        await asyncio.sleep(0.001)
    assert await tc.set_execution_mode(ExecutionMode.CONTINUOUS) == Status.OK
    assert await tc.load_by_name("spin") == Status.OK
    assert await tc.start() == Status.OK

    async def spin_a_while() -> None:
        robot = cell.equipment
        start = robot.cycles  # type: ignore[attr-defined]
        while robot.cycles < start + 200:  # type: ignore[attr-defined]
            await asyncio.sleep(0.001)

    _, lag = await _loop_lag_during(asyncio.wait_for(spin_a_while(), 10))
    assert lag < 0.5
    assert await tc.stop(StopMode.QUICK_STOP) == Status.OK
    await asyncio.wait_for(tc.wait_until_not_executing(), 5)
    assert tc.state == "Ready"


# --- the log under a flood ------------------------------------------------------------------------
def test_repeated_identical_errors_are_rate_limited() -> None:
    """At most ``burst`` identical lines and ``similar`` lines of one template a window; the next line
    let through says how many of each were dropped."""
    import logging

    from uacell.core.logs import RepeatFilter

    now = [0.0]
    repeat = RepeatFilter(burst=3, similar=5, window=60.0, clock=lambda: now[0])
    logger = logging.getLogger("uacell.test.flood")
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep()
    handler.addFilter(repeat)
    logger.addHandler(handler)
    logger.propagate = False
    logger.setLevel(logging.INFO)
    try:
        for i in range(1000):  # a flood whose arguments vary: one template
            logger.error("socket.accept() out of system resource (%d)", i)
        for _ in range(10):  # one line again and again
            logger.warning("the disk is full")
        for plc in ("a", "b", "c", "d"):  # one kind of fault from four sources: each said
            logger.warning("the PLC at %s: lost the connection (retrying)", plc)
        logger.info("info is never limited %d", 1)
        logger.info("info is never limited %d", 2)
        assert [r.getMessage() for r in records] == [
            *(f"socket.accept() out of system resource ({i})" for i in range(5)),
            "the disk is full",
            "the disk is full",
            "the disk is full",
            *(f"the PLC at {plc}: lost the connection (retrying)" for plc in "abcd"),
            "info is never limited 1",
            "info is never limited 2",
        ]
        now[0] = 61.0
        logger.error("socket.accept() out of system resource (%d)", 1000)
        logger.warning("the disk is full")
        logger.warning("the PLC at %s: lost the connection (retrying)", "a")
        assert [r.getMessage() for r in records[-3:]] == [
            "socket.accept() out of system resource (1000) [995 similar messages suppressed]",
            "the disk is full [7 identical messages suppressed]",
            "the PLC at a: lost the connection (retrying)",
        ]
    finally:
        logger.removeHandler(handler)
        logger.propagate = True
