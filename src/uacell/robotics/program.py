"""The uacell robot program format: small, line-based, written by hand (see docs/programs.md).

A file is a *program* (what a task control runs) or a *module* (routines that programs call)::

    program PickAndPlace version 1.0
    use Gripper
    speed 50
    move 0 -20 30 0 45 0
    call Gripper.pick
    repeat 3
      move 45 -10 20 0 40 0
      wait 0.5
    end

``parse`` turns text into a ``Program`` or raises ``ProgramError`` naming the line and the reason.
``expand`` resolves calls and loops against the loaded modules into the flat list of ``Step`` that
the robot executes; a program pointer is an index into that list. ``measure`` counts those steps
without building them (its cost grows with the text, not with the loops).

``ProgramLimits`` bounds everything a file can make the server do: its size and line count, how deep
blocks nest, how many steps it expands to, how deep calls nest and how many instructions checking and
expanding may visit. A program beyond them raises ``ProgramTooLarge`` (a ``ProgramError``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from importlib import resources
from typing import Protocol

AXIS_COUNT = 6
MAX_SPEED_PERCENT = 100.0
MAX_WAIT_SECONDS = 3600.0
MAX_REPEAT = 10_000
MAX_STEPS = 20_000  # after expansion; keeps a runaway nesting of loops from exhausting memory
MAX_CALL_DEPTH = 16

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_VERSION = re.compile(r"[A-Za-z0-9_.+\-]+\Z")
_CALL = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\.([A-Za-z_][A-Za-z0-9_]*)\Z")


class ProgramError(ValueError):
    """The text is not a valid program or module; ``line`` is 1-based (0 when not tied to a line)."""

    def __init__(self, line: int, reason: str) -> None:
        super().__init__(f"line {line}: {reason}" if line else reason)
        self.line = line
        self.reason = reason


class ProgramTooLarge(ProgramError):
    """The text is beyond a ``ProgramLimits`` bound (size, lines, nesting, steps, call depth, work)."""


class NothingToExecute(ProgramError):
    """The program, with its calls resolved, has no move or wait: there is nothing to run."""


@dataclass(frozen=True)
class ProgramLimits:
    """What one program or module may cost the server (docs/programs.md, ``[programs]`` configuration)."""

    max_file_bytes: int = 128 * 1024  # size of a file's text
    max_lines: int = 10_000  # lines of a file, comments and blank lines included
    max_nesting: int = 16  # repeat (and routine) blocks open at once
    max_steps: int = MAX_STEPS  # moves and waits after loops are unrolled and calls inlined
    max_call_depth: int = MAX_CALL_DEPTH  # calls nested in calls
    max_work: int = 200_000  # instructions visited while checking and expanding one program

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, not {value!r}")


DEFAULT_LIMITS = ProgramLimits()


class Kind(StrEnum):
    PROGRAM = "program"
    MODULE = "module"


@dataclass(frozen=True)
class Move:
    """Joint move of all six axes to absolute positions in degrees."""

    line: int
    joints: tuple[float, ...]


@dataclass(frozen=True)
class Speed:
    """Speed override in percent of each axis's maximum speed, for the moves that follow."""

    line: int
    percent: float


@dataclass(frozen=True)
class Wait:
    line: int
    seconds: float


@dataclass(frozen=True)
class Call:
    line: int
    module: str
    routine: str


@dataclass(frozen=True)
class Repeat:
    line: int
    count: int
    body: tuple[Instruction, ...]


Instruction = Move | Speed | Wait | Call | Repeat


@dataclass(frozen=True)
class Program:
    """A parsed program or module."""

    name: str
    kind: Kind
    version: str
    instructions: tuple[Instruction, ...]  # a module's main body is always empty
    uses: tuple[str, ...]  # referenced modules, in order of their `use` lines
    routines: Mapping[str, tuple[Instruction, ...]] = field(default_factory=dict)
    source: str = field(default="", repr=False, compare=False)

    @property
    def referenced_modules(self) -> tuple[str, ...]:
        return self.uses


@dataclass(frozen=True)
class Step:
    """One executable instruction after expansion: a move or a wait.

    ``speed`` is the override in force for a move. ``group`` numbers the top-level call a step belongs
    to (``None`` outside calls): a ProcessStop finishes the group so a tool sequence is never cut.
    """

    kind: str  # "move" | "wait"
    line: int
    origin: str  # name of the program or module the line is in
    joints: tuple[float, ...] = ()
    speed: float = MAX_SPEED_PERCENT
    seconds: float = 0.0
    group: int | None = None


def _number(token: str, line: int, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise ProgramError(line, f"{what}: {token!r} is not a number") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ProgramError(line, f"{what}: {token!r} is not a finite number")
    return value


def parse(
    text: str,
    limits: Sequence[tuple[float, float]] | None = None,
    *,
    bounds: ProgramLimits = DEFAULT_LIMITS,
) -> Program:
    """Parse a program or module. ``limits`` are the (min, max) degrees of each axis, if known;
    ``bounds`` the size, line and nesting limits (``ProgramTooLarge`` beyond them).

    A ``move`` gives one position per axis: as many as ``limits`` has, else ``AXIS_COUNT``. Empty
    ``limits`` mean there is nothing to move (a controller without a motion device): ``move`` is refused.
    """
    axis_count = len(limits) if limits is not None else AXIS_COUNT
    if len(text) > bounds.max_file_bytes or len(text.encode("utf-8", "surrogatepass")) > bounds.max_file_bytes:
        raise ProgramTooLarge(0, f"the file is larger than {bounds.max_file_bytes} bytes")
    lines = text.splitlines()
    if len(lines) > bounds.max_lines:
        raise ProgramTooLarge(0, f"the file has more than {bounds.max_lines} lines")
    header: tuple[Kind, str, str] | None = None
    uses: list[str] = []
    routines: dict[str, tuple[Instruction, ...]] = {}
    # Block stack: (keyword, line, name or count, body being collected).
    main: list[Instruction] = []
    stack: list[tuple[str, int, str | int, list[Instruction]]] = []
    calls: list[Call] = []

    def body() -> list[Instruction]:
        return stack[-1][3] if stack else main

    for number, raw in enumerate(lines, start=1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        keyword, args = words[0].lower(), words[1:]
        if header is None:
            if keyword not in (Kind.PROGRAM, Kind.MODULE):
                raise ProgramError(number, "expected header 'program NAME' or 'module NAME'")
            if len(args) not in (1, 3) or (len(args) == 3 and args[1].lower() != "version"):
                raise ProgramError(number, f"header must be '{keyword} NAME [version V]'")
            if not _NAME.match(args[0]):
                raise ProgramError(number, f"invalid name {args[0]!r}")
            version = args[2] if len(args) == 3 else ""
            if version and not _VERSION.match(version):
                raise ProgramError(number, f"invalid version {version!r}")
            header = (Kind(keyword), args[0], version)
            continue
        kind = header[0]

        def expect(n: int, usage: str, kw: str = keyword, got: list[str] = args, ln: int = number) -> None:
            if len(got) != n:
                raise ProgramError(ln, f"'{kw}' takes {usage}")

        if kind is Kind.MODULE and not stack and keyword in ("move", "speed", "wait", "call", "repeat"):
            raise ProgramError(number, f"'{keyword}' outside a routine (a module holds 'use' and 'routine')")
        if keyword in (Kind.PROGRAM, Kind.MODULE):
            raise ProgramError(number, "a file holds one program or module; second header found")
        elif keyword == "use":
            expect(1, "one module name")
            if stack:
                raise ProgramError(number, "'use' must be at top level")
            if not _NAME.match(args[0]):
                raise ProgramError(number, f"invalid module name {args[0]!r}")
            if args[0] == header[1]:
                raise ProgramError(number, f"{header[1]} cannot use itself")
            if args[0] not in uses:
                uses.append(args[0])
        elif keyword == "move":
            if not axis_count:
                raise ProgramError(number, "'move' needs a motion device, and this controller moves none")
            if len(args) != axis_count:
                raise ProgramError(number, f"'move' takes {axis_count} joint positions in degrees")
            joints = tuple(_number(a, number, f"axis {i + 1}") for i, a in enumerate(args))
            for i, (value, lim) in enumerate(zip(joints, limits or (), strict=False)):
                if not lim[0] <= value <= lim[1]:
                    raise ProgramError(
                        number,
                        f"axis {i + 1} position {value:g} is outside its limits {lim[0]:g}..{lim[1]:g}",
                    )
            body().append(Move(number, joints))
        elif keyword == "speed":
            expect(1, "one percentage")
            percent = _number(args[0], number, "speed")
            if not 0 < percent <= MAX_SPEED_PERCENT:
                raise ProgramError(number, f"speed {percent:g} must be above 0 and at most 100 percent")
            body().append(Speed(number, percent))
        elif keyword == "wait":
            expect(1, "one duration in seconds")
            seconds = _number(args[0], number, "wait")
            if not 0 <= seconds <= MAX_WAIT_SECONDS:
                raise ProgramError(number, f"wait {seconds:g} must be between 0 and {MAX_WAIT_SECONDS:g} s")
            body().append(Wait(number, seconds))
        elif keyword == "call":
            expect(1, "MODULE.ROUTINE")
            m = _CALL.match(args[0])
            if not m:
                raise ProgramError(number, f"call target {args[0]!r} must be MODULE.ROUTINE")
            call = Call(number, m.group(1), m.group(2))
            if call.module != header[1] and call.module not in uses:
                raise ProgramError(number, f"call into {call.module} needs 'use {call.module}' first")
            calls.append(call)
            body().append(call)
        elif keyword == "repeat":
            expect(1, "a count")
            count = _number(args[0], number, "repeat")
            if count != int(count) or not 1 <= count <= MAX_REPEAT:
                raise ProgramError(number, f"repeat count must be a whole number from 1 to {MAX_REPEAT}")
            if len(stack) >= bounds.max_nesting:
                raise ProgramTooLarge(number, f"blocks nest deeper than {bounds.max_nesting}")
            stack.append(("repeat", number, int(count), []))
        elif keyword == "routine":
            expect(1, "a name")
            if kind is not Kind.MODULE:
                raise ProgramError(number, "routines are defined in modules only")
            if stack:
                raise ProgramError(number, "'routine' must be at top level")
            if not _NAME.match(args[0]):
                raise ProgramError(number, f"invalid routine name {args[0]!r}")
            if args[0] in routines:
                raise ProgramError(number, f"routine {args[0]} is defined twice")
            stack.append(("routine", number, args[0], []))
        elif keyword == "end":
            expect(0, "no arguments")
            if not stack:
                raise ProgramError(number, "'end' without 'repeat' or 'routine'")
            block, start, what, collected = stack.pop()
            if block == "routine":
                routines[str(what)] = tuple(collected)
            else:
                body().append(Repeat(start, int(what), tuple(collected)))
        else:
            raise ProgramError(number, f"unknown statement {words[0]!r}")
    if header is None:
        raise ProgramError(0, "empty file: expected header 'program NAME' or 'module NAME'")
    if stack:
        block, start, _, _ = stack[-1]
        raise ProgramError(start, f"'{block}' is not closed with 'end'")
    for call in calls:
        if call.module == header[1] and call.routine not in routines:
            raise ProgramError(call.line, f"routine {call.routine} is not defined in {header[1]}")
    kind, name, version = header
    if kind is Kind.PROGRAM and not main:
        raise ProgramError(0, f"program {name} has no instructions")
    return Program(name, kind, version, tuple(main), tuple(uses), routines, text)


class _Measure:
    """Step counts of instruction lists and routines, each computed once (cost: the text, not the loops)."""

    def __init__(self, program: Program, modules: Mapping[str, Program], bounds: ProgramLimits, partial: bool) -> None:
        self.program, self.modules, self.bounds, self.partial = program, modules, bounds, partial
        self.sizes: dict[int, int] = {}  # id(Repeat) -> steps of one pass of its body
        self.routines: dict[tuple[str, str], tuple[int, int]] = {}  # -> (steps, call height)
        self.busy: set[tuple[str, str]] = set()
        self.unresolved = False
        self.work = 0

    def visit(self, count: int = 1) -> None:
        self.work += count
        if self.work > self.bounds.max_work:
            limit = self.bounds.max_work
            raise ProgramTooLarge(0, f"{self.program.name} takes more than {limit} instructions to expand")

    def cap(self, steps: int) -> int:
        # Beyond the limit the exact number does not matter: keeps the integers small.
        return min(steps, self.bounds.max_steps + 1)

    def target(self, call: Call, origin: str) -> Program | None:
        target = self.program if call.module == self.program.name else self.modules.get(call.module)
        if target is None or target.kind is not Kind.MODULE:
            if self.partial:
                return None
            raise ProgramError(call.line, f"module {call.module} is not loaded ({origin})")
        if call.routine not in target.routines:
            if self.partial:
                return None
            raise ProgramError(call.line, f"module {call.module} has no routine {call.routine} ({origin})")
        return target

    def items(self, items: Sequence[Instruction], origin: str) -> tuple[int, int]:
        """(steps, call height) of ``items``."""
        steps = height = 0
        for item in items:
            self.visit()
            if isinstance(item, Move | Wait):
                steps += 1
            elif isinstance(item, Repeat):
                body, h = self.items(item.body, origin)
                self.sizes[id(item)] = body
                steps, height = steps + item.count * body, max(height, h)
            elif isinstance(item, Call):
                target = self.target(item, origin)
                if target is None:
                    self.unresolved = True
                    continue
                body, h = self.routine(item, target, origin)
                steps, height = steps + body, max(height, h + 1)
            steps = self.cap(steps)
        return steps, height

    def routine(self, call: Call, target: Program, origin: str) -> tuple[int, int]:
        key = (call.module, call.routine)
        known = self.routines.get(key)
        if known is not None:
            return known
        if key in self.busy:  # a routine that calls itself, directly or not, nests without end
            raise ProgramError(call.line, f"calls nest deeper than {self.bounds.max_call_depth} ({origin})")
        self.busy.add(key)
        result = self.items(target.routines[call.routine], call.module)
        self.busy.discard(key)
        if result[1] + 1 > self.bounds.max_call_depth:
            raise ProgramError(call.line, f"calls nest deeper than {self.bounds.max_call_depth} ({origin})")
        self.routines[key] = result
        return result

    def total(self) -> int:
        program = self.program
        if program.kind is Kind.MODULE:
            steps = 0
            for name in program.routines:
                steps = max(steps, self.routine(Call(0, program.name, name), program, program.name)[0])
        else:
            steps, _ = self.items(program.instructions, program.name)
        if steps > self.bounds.max_steps:
            raise ProgramTooLarge(0, f"{program.name} expands to more than {self.bounds.max_steps} steps")
        if steps == 0 and program.kind is Kind.PROGRAM and not self.unresolved:
            raise NothingToExecute(0, f"{program.name} has no move or wait to execute")
        return steps


def measure(
    program: Program,
    modules: Mapping[str, Program],
    bounds: ProgramLimits = DEFAULT_LIMITS,
    *,
    partial: bool = False,
) -> int:
    """How many steps ``expand`` gives (for a module: its largest routine), without building them.

    Raises what ``expand`` raises. With ``partial`` calls that do not resolve (yet) count as no step
    instead of failing: the check at load time, before the modules are known.
    """
    m = _Measure(program, modules, bounds, partial)
    try:
        return m.total()
    except RecursionError:  # only with limits raised far beyond their defaults
        raise ProgramTooLarge(0, f"{program.name} nests too deeply to check") from None


def expand(
    program: Program, modules: Mapping[str, Program], bounds: ProgramLimits = DEFAULT_LIMITS
) -> tuple[Step, ...]:
    """The flat steps of ``program`` with calls resolved in ``modules`` (by name) and loops unrolled.

    Raises ``ProgramError`` (at the calling line) when a module is not loaded, a routine is missing or
    calls recurse too deeply, and ``ProgramTooLarge`` when the expansion is beyond ``bounds``.
    """
    m = _Measure(program, modules, bounds, partial=False)
    try:
        m.total()
    except RecursionError:
        raise ProgramTooLarge(0, f"{program.name} nests too deeply to check") from None
    steps: list[Step] = []
    groups = 0

    def walk(items: Sequence[Instruction], origin: str, speed: float, group: int | None) -> float:
        nonlocal groups
        for item in items:
            m.visit()
            match item:
                case Move(line, joints):
                    steps.append(Step("move", line, origin, joints=joints, speed=speed, group=group))
                case Wait(line, seconds):
                    steps.append(Step("wait", line, origin, seconds=seconds, speed=speed, group=group))
                case Speed(_, percent):
                    speed = percent
                case Repeat(_, count, body):
                    # A body without steps only changes the speed: one pass has the effect of all.
                    for _ in range(count if m.sizes[id(item)] else 1):
                        speed = walk(body, origin, speed, group)
                case Call(_, module, routine):
                    if not m.routines[(module, routine)][0]:
                        continue  # a routine's speed changes stay inside it: nothing to do
                    target = program if module == program.name else modules[module]
                    if group is None:
                        groups += 1
                    # A routine's speed changes stay inside it, like a local setting.
                    walk(target.routines[routine], module, speed, group or groups)
        return speed

    walk(program.instructions, program.name, MAX_SPEED_PERCENT, None)
    return tuple(steps)


def samples() -> dict[str, str]:
    """The sample programs and modules shipped with uacell: file name -> text."""
    folder = resources.files("uacell") / "samples"
    return {f.name: f.read_text(encoding="utf-8") for f in folder.iterdir() if f.name.endswith(".robot")}


class AxisRange(Protocol):
    """What a generated program needs of an axis (``robotics.equipment.AxisInfo`` has it)."""

    @property
    def min_position(self) -> float: ...

    @property
    def max_position(self) -> float: ...


def wave_program(axes: Sequence[AxisRange]) -> str:
    """A program for any arm: home, each axis a little way out and back, home."""
    home = [0.0 if a.min_position <= 0.0 <= a.max_position else a.min_position for a in axes]
    lines = [f"# Wave: generated for a {len(axes)}-axis arm", "program Wave version 1.0", "speed 50"]

    def move(values: Sequence[float]) -> str:
        return "move " + " ".join(f"{v:g}" for v in values)

    lines.append(move(home))
    for i, a in enumerate(axes):
        out = list(home)
        out[i] = home[i] + min(20.0, (a.max_position - home[i]) / 2)
        lines += [move(out), move(home)]
    return "\n".join(lines) + "\n"
