"""A simulated six-axis robot implementing ``RobotEquipment``.

Moves are synchronized joint moves: every axis arrives at the same time, the slowest axis going at its
maximum speed times the speed override. Positions are computed from the clock, so reading them costs
nothing and they are exact at any instant. ``time_scale`` is real seconds per simulated second
(0.001 makes a 2 s power-up take 2 ms in tests).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.robotics.equipment import (
    AlarmListener,
    AlarmStop,
    AxisInfo,
    AxisState,
    EquipmentError,
    ExecutionMode,
    NotPowered,
    Progress,
    RunOutcome,
    StopMode,
)
from uacell.robotics.program import DEFAULT_LIMITS, Kind, Program, ProgramError, ProgramLimits, Step, expand

log = logging.getLogger(__name__)

# A small industrial arm (ABB IRB 1200 class): limits in degrees, maximum speeds in degrees/s.
DEFAULT_AXES: tuple[AxisInfo, ...] = (
    AxisInfo("A1", -170.0, 170.0, 288.0),
    AxisInfo("A2", -100.0, 135.0, 240.0),
    AxisInfo("A3", -200.0, 70.0, 300.0),
    AxisInfo("A4", -270.0, 270.0, 400.0),
    AxisInfo("A5", -130.0, 130.0, 405.0),
    AxisInfo("A6", -400.0, 400.0, 600.0),
)
DEFAULT_ALARMS = ("EmergencyStop", "CollisionDetected")
BRAKE_TIME = 0.2  # simulated seconds an OnPath stop takes to brake along the path


@dataclass
class _Segment:
    """Motion from ``start`` by ``delta`` over ``duration`` simulated seconds from ``t0``.

    ``braking`` segments decelerate linearly to zero (the distance covered is v*duration/2).
    """

    start: tuple[float, ...]
    delta: tuple[float, ...]
    t0: float
    duration: float
    braking: bool = False

    def fraction(self, now: float) -> float:
        f = 1.0 if self.duration <= 0 else min(1.0, max(0.0, (now - self.t0) / self.duration))
        return f * (2.0 - f) if self.braking else f

    def positions(self, now: float) -> tuple[float, ...]:
        f = self.fraction(now)
        return tuple(s + d * f for s, d in zip(self.start, self.delta, strict=True))

    def speeds(self, now: float) -> tuple[float, ...]:
        if self.duration <= 0 or now >= self.t0 + self.duration:
            return tuple(0.0 for _ in self.delta)
        f = max(0.0, (now - self.t0) / self.duration)
        factor = 2.0 * (1.0 - f) if self.braking else 1.0
        return tuple(d / self.duration * factor for d in self.delta)


@dataclass
class _Task:
    program: Program | None = None
    modules: dict[str, Program] | None = None
    stop: StopMode | None = None
    alarm: str | None = None
    wake: asyncio.Event | None = None
    running: bool = False


class SimulatedRobot:
    """The built-in robot: one six-axis arm, drive power, programs per task, alarms."""

    def __init__(
        self,
        *,
        time_scale: float = 1.0,
        power_up_time: float = 2.0,
        power_down_time: float = 0.5,
        axes: Sequence[AxisInfo] = DEFAULT_AXES,
        alarms: Sequence[str] = DEFAULT_ALARMS,
        home: Sequence[float] | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], Awaitable[None]] | None = None,
        program_limits: ProgramLimits = DEFAULT_LIMITS,
    ) -> None:
        """``clock`` (seconds) and ``sleep`` default to the event loop's; tests inject a virtual pair
        (``clock`` must advance by what ``sleep`` waits) so that nothing depends on wall time."""
        if time_scale <= 0:
            raise ValueError("time_scale must be positive")
        self.time_scale = time_scale
        self._clock = clock
        self._sleep_for = sleep or asyncio.sleep
        self.program_limits = program_limits
        self.power_up_time = power_up_time
        self.power_down_time = power_down_time
        self._axes = tuple(axes)
        self._alarm_names = tuple(alarms)
        self.active_alarms: dict[str, str] = {}
        self._alarm_listeners: list[AlarmListener] = []
        self.powered = False
        self.fail_power_up = False  # test hook: the next power_up raises EquipmentError
        start = tuple(home) if home is not None else tuple(0.0 for _ in self._axes)
        self._segment = _Segment(start, tuple(0.0 for _ in start), 0.0, 0.0)
        self._tasks: dict[str, _Task] = {}
        self.cycles = 0  # completed program cycles, all tasks

    # --- time -------------------------------------------------------------------------------
    def _now(self) -> float:
        """Simulated seconds."""
        now = self._clock() if self._clock is not None else asyncio.get_running_loop().time()
        return now / self.time_scale

    def _now_or_zero(self) -> float:
        try:
            return self._now()
        except RuntimeError:  # read outside an event loop: nothing is moving then
            return self._segment.t0 + self._segment.duration

    async def _sleep(self, sim_seconds: float) -> None:
        await self._sleep_for(max(0.0, sim_seconds) * self.time_scale)

    # --- description and alarms -------------------------------------------------------------
    @property
    def axes(self) -> Sequence[AxisInfo]:
        return self._axes

    @property
    def alarm_names(self) -> Sequence[str]:
        return self._alarm_names

    def add_alarm_listener(self, listener: AlarmListener) -> None:
        self._alarm_listeners.append(listener)

    def raise_alarm(self, name: str, message: str = "") -> None:
        """Make alarm ``name`` active: running programs stop at once (QuickStop) with ``AlarmStop``."""
        if name not in self._alarm_names:
            raise KeyError(f"unknown alarm {name!r}")
        self.active_alarms[name] = message or name
        for task in self._tasks.values():
            if task.running:
                task.alarm = name
                task.stop = StopMode.QUICK_STOP
                if task.wake:
                    task.wake.set()
        for listener in list(self._alarm_listeners):
            listener(name, True, self.active_alarms[name])

    def clear_alarm(self, name: str) -> None:
        """Make alarm ``name`` inactive (it may still need acknowledging in SystemOperation)."""
        message = self.active_alarms.pop(name, None)
        if message is not None:
            for listener in list(self._alarm_listeners):
                listener(name, False, message)

    # --- axes -------------------------------------------------------------------------------
    def axis_states(self) -> Sequence[AxisState]:
        now = self._now_or_zero()
        return tuple(
            AxisState(p, v) for p, v in zip(self._segment.positions(now), self._segment.speeds(now), strict=True)
        )

    @property
    def positions(self) -> tuple[float, ...]:
        return tuple(a.position for a in self.axis_states())

    @property
    def moving(self) -> bool:
        return any(a.speed != 0.0 for a in self.axis_states())

    def _freeze(self) -> None:
        now = self._now()
        here = self._segment.positions(now)
        self._segment = _Segment(here, tuple(0.0 for _ in here), now, 0.0)

    # --- power ------------------------------------------------------------------------------
    async def power_up(self) -> None:
        await self._sleep(self.power_up_time)
        if self.fail_power_up:
            self.fail_power_up = False
            raise EquipmentError("drive power did not come up")
        if self.active_alarms:
            raise EquipmentError(f"alarm active: {', '.join(self.active_alarms)}")
        self.powered = True

    async def power_down(self) -> None:
        for name, task in self._tasks.items():
            if task.running:
                await self.stop(name, StopMode.QUICK_STOP)
        await self._sleep(self.power_down_time)
        self.powered = False

    # --- programs ---------------------------------------------------------------------------
    def _task(self, task: str) -> _Task:
        return self._tasks.setdefault(task, _Task(modules={}))

    async def load(self, task: str, program: Program) -> None:
        t = self._task(task)
        if t.running:
            raise EquipmentError(f"{task} is running")
        if program.kind is Kind.PROGRAM:
            t.program = program
        else:
            assert t.modules is not None
            t.modules[program.name] = program

    async def unload(self, task: str, name: str) -> None:
        t = self._task(task)
        if t.running:
            raise EquipmentError(f"{task} is running")
        assert t.modules is not None
        if t.program is not None and t.program.name == name:
            t.program = None
        elif t.modules.pop(name, None) is None:
            raise EquipmentError(f"{name} is not loaded on {task}")

    async def stop(self, task: str, mode: StopMode) -> None:
        t = self._task(task)
        # Kept even before the run's first instruction: the model may ask to stop a run it has just
        # started whose coroutine has not begun yet. run() clears it when it ends.
        t.stop = StopMode(mode)
        if t.wake:
            t.wake.set()

    async def run(self, task: str, pointer: int, mode: ExecutionMode, progress: Progress) -> RunOutcome:
        t = self._task(task)
        if t.running:
            raise EquipmentError(f"{task} is already running")
        if not self.powered:
            t.stop = None
            raise NotPowered("drive power is off")
        if t.program is None:
            t.stop = None
            raise EquipmentError(f"no program loaded on {task}")
        if self.active_alarms:
            # Raised between the Start and this run's first step: raise_alarm saw no running task.
            t.stop = None
            raise AlarmStop(f"alarm {', '.join(self.active_alarms)} is active")
        program = t.program
        t.running, t.alarm, t.wake = True, None, asyncio.Event()
        try:
            # Off the event loop: expansion is bounded by program_limits but may take a moment.
            try:
                steps = await asyncio.to_thread(expand, program, dict(t.modules or {}), self.program_limits)
            except ProgramError as e:
                raise EquipmentError(f"{program.name}: {e}") from e
            if t.alarm:  # raised while expanding
                raise AlarmStop(f"alarm {t.alarm} is active")
            return await self._run(t, steps, pointer if 0 <= pointer < len(steps) else 0, mode, progress)
        finally:
            t.running, t.wake, t.stop = False, None, None

    async def _run(
        self, t: _Task, steps: Sequence[Step], i: int, mode: ExecutionMode, progress: Progress
    ) -> RunOutcome:
        while True:
            step = steps[i]
            progress(i, step.line)
            finished = await self._execute(t, step)
            # A step may take no time at all (wait 0, a move to where the arm is): let others run.
            await asyncio.sleep(0)
            if t.alarm:
                raise AlarmStop(f"alarm {t.alarm} stopped the robot at line {step.line} of {step.origin}")
            if not finished:  # QuickStop / OnPath cut the instruction: resume redoes it
                return RunOutcome(i, False)
            i += 1
            if i == len(steps):
                self.cycles += 1
                if mode is ExecutionMode.CONTINUOUS and t.stop is None:
                    i = 0
                    continue
                return RunOutcome(0, True)
            if t.stop in (StopMode.END_OF_INSTRUCTION, StopMode.QUICK_STOP, StopMode.ON_PATH):
                return RunOutcome(i, False)
            if t.stop is StopMode.PROCESS_STOP and (step.group is None or steps[i].group != step.group):
                return RunOutcome(i, False)
            if mode is ExecutionMode.STEP:
                return RunOutcome(i, False)

    async def _wait_or_stop(self, t: _Task, sim_seconds: float) -> bool:
        """Sleep; True if woken by a stop request first."""
        assert t.wake is not None
        if t.stop is not None and t.stop in (StopMode.QUICK_STOP, StopMode.ON_PATH):
            return True
        t.wake.clear()
        delay = max(0.0, sim_seconds) * self.time_scale
        if self._sleep_for is not asyncio.sleep:  # injected time: race its sleep against the stop
            return await self._race(t.wake, delay)
        # asyncio.timeout, not wait_for: 3.11's wait_for loses a cancel that races a set event.
        try:
            async with asyncio.timeout(delay):
                await t.wake.wait()
        except TimeoutError:
            return False
        return True

    async def _race(self, wake: asyncio.Event, delay: float) -> bool:
        sleeper = asyncio.ensure_future(self._sleep_for(delay))
        waker = asyncio.ensure_future(wake.wait())
        try:
            await asyncio.wait({sleeper, waker}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (sleeper, waker):
                task.cancel()
            await asyncio.gather(sleeper, waker, return_exceptions=True)
        return wake.is_set()

    async def _execute(self, t: _Task, step: Step) -> bool:
        """Carry out one step; False if a stop cut it short."""
        if step.kind == "wait":
            end = self._now() + step.seconds
            while (left := end - self._now()) > 0:
                if await self._wait_or_stop(t, left) and t.stop in (StopMode.QUICK_STOP, StopMode.ON_PATH):
                    return False
            return True
        now = self._now()
        here = self._segment.positions(now)
        delta = tuple(target - p for target, p in zip(step.joints, here, strict=True))
        speeds = (axis.max_speed * step.speed / 100.0 for axis in self._axes)
        duration = max((abs(d) / v for d, v in zip(delta, speeds, strict=True)), default=0.0)
        self._segment = _Segment(here, delta, now, duration)
        while (left := self._segment.t0 + self._segment.duration - self._now()) > 0:
            if not await self._wait_or_stop(t, left):
                continue
            if t.stop is StopMode.QUICK_STOP:
                self._freeze()
                return False
            if t.stop is StopMode.ON_PATH:
                return await self._brake(t)
        # Arrive exactly: no rounding drift accumulates over a long CONTINUOUS run.
        self._segment = _Segment(step.joints, tuple(0.0 for _ in step.joints), self._now(), 0.0)
        return True

    async def _brake(self, t: _Task) -> bool:
        """Decelerate along the path over BRAKE_TIME; True if the move's target is reached anyway."""
        now = self._now()
        seg = self._segment
        remaining = 1.0 - seg.fraction(now)
        speeds = seg.speeds(now)
        # Distance to brake from speed v in BRAKE_TIME: v*T/2 (as a fraction of the whole move).
        needed = (BRAKE_TIME / 2.0) / seg.duration if seg.duration > 0 else 0.0
        if any(speeds) and needed < remaining:
            here = seg.positions(now)
            self._segment = _Segment(here, tuple(v * BRAKE_TIME / 2.0 for v in speeds), now, BRAKE_TIME, True)
            await self._sleep(BRAKE_TIME)
            self._freeze()
            return False
        # The target is within braking distance: finish the move.
        await self._sleep(seg.t0 + seg.duration - now)
        self._freeze()
        return True


# What the ``settings`` table of a simulated controller may hold (docs/configuration.md).
SIMULATOR_SETTINGS = ("time_scale", "power_up_time", "power_down_time", "alarms")


def simulator(spec: Any) -> SimulatedRobot:
    """The equipment factory of a simulated controller (``uacell.robotics.sim:simulator``).

    ``spec`` is a ``uacell.robotics.equipment.ControllerEquipmentSpec``: its ``axes`` are the configured axes of the
    motion device (the six default ones if empty), its ``settings`` may set ``time_scale`` (> 1 runs
    faster than real time), ``power_up_time``/``power_down_time`` (simulated seconds) and ``alarms``
    (the alarm names).
    """
    settings = dict(spec.settings)
    unknown = sorted(set(settings) - set(SIMULATOR_SETTINGS))
    if unknown:
        raise ValueError(f"the simulator has no setting {unknown[0]!r} (it knows {', '.join(SIMULATOR_SETTINGS)})")
    scale = float(settings.get("time_scale", 1.0))
    if scale <= 0:
        raise ValueError("time_scale must be greater than 0")
    alarms = settings.get("alarms", DEFAULT_ALARMS)
    if not isinstance(alarms, list | tuple) or not all(isinstance(a, str) for a in alarms):
        raise ValueError("alarms must be an array of names")
    return SimulatedRobot(
        time_scale=1.0 / scale,  # SimulatedRobot counts real seconds per simulated second
        power_up_time=float(settings.get("power_up_time", 2.0)),
        power_down_time=float(settings.get("power_down_time", 0.5)),
        axes=tuple(getattr(spec, "axes", ())) or DEFAULT_AXES,
        alarms=tuple(alarms),
    )
