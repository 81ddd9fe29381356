"""The robot program format: parsing, errors with line numbers, expansion, samples."""

from __future__ import annotations

import pytest

from uacell.robotics.program import (
    Call,
    Kind,
    Move,
    ProgramError,
    Repeat,
    Speed,
    Wait,
    expand,
    parse,
    samples,
)
from uacell.robotics.sim import DEFAULT_AXES

LIMITS = [a.limits for a in DEFAULT_AXES]

MODULE = """\
module Tool version 3
routine grip
  speed 25
  move 0 0 0 0 10 0
  wait 0.1
end
routine twice
  call Tool.grip
  call Tool.grip
end
"""


def test_program_with_every_statement() -> None:
    p = parse(
        """# demo
program Demo version 1.0-b   # trailing comment
use Tool

SPEED 40
move 1 2 3 4 5 6
wait 0.5
call Tool.grip
repeat 2
  move 0 0 0 0 0 0
end
""",
        LIMITS,
    )
    assert (p.name, p.kind, p.version, p.uses) == ("Demo", Kind.PROGRAM, "1.0-b", ("Tool",))
    assert p.referenced_modules == ("Tool",)
    assert p.instructions == (
        Speed(5, 40.0),
        Move(6, (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)),
        Wait(7, 0.5),
        Call(8, "Tool", "grip"),
        Repeat(9, 2, (Move(10, (0.0,) * 6),)),
    )


def test_module_routines() -> None:
    m = parse(MODULE, LIMITS)
    assert (m.name, m.kind, m.version, m.instructions) == ("Tool", Kind.MODULE, "3", ())
    assert set(m.routines) == {"grip", "twice"}
    assert m.routines["twice"] == (Call(8, "Tool", "grip"), Call(9, "Tool", "grip"))


def test_version_is_optional() -> None:
    assert parse("program P\nwait 0\n").version == ""


@pytest.mark.parametrize(
    ("text", "line", "reason"),
    [
        ("", 0, "empty file"),
        ("# only a comment\n", 0, "empty file"),
        ("move 0 0 0 0 0 0\n", 1, "expected header"),
        ("program\n", 1, "header must be"),
        ("program P release 2\n", 1, "header must be"),
        ("program 9P\n", 1, "invalid name"),
        ("program P\n", 0, "has no instructions"),
        ("program P\njump 3\n", 2, "unknown statement 'jump'"),
        ("program P\nmove 0 0 0 0 0\n", 2, "6 joint positions"),
        ("program P\nmove 0 0 x 0 0 0\n", 2, "axis 3: 'x' is not a number"),
        ("program P\nmove 0 0 nan 0 0 0\n", 2, "not a finite number"),
        ("program P\n\nmove 171 0 0 0 0 0\n", 3, "axis 1 position 171 is outside its limits -170..170"),
        ("program P\nmove 0 0 0 0 0 -400.5\n", 2, "axis 6 position -400.5"),
        ("program P\nspeed 0\n", 2, "speed 0 must be above 0"),
        ("program P\nspeed 101\n", 2, "at most 100"),
        ("program P\nwait -1\n", 2, "wait -1 must be between"),
        ("program P\nwait\n", 2, "'wait' takes"),
        ("program P\ncall Tool.grip\n", 2, "needs 'use Tool'"),
        ("program P\nuse Tool\ncall grip\n", 3, "must be MODULE.ROUTINE"),
        ("program P\nrepeat 2.5\nwait 0\nend\n", 2, "whole number"),
        ("program P\nrepeat 2\nwait 0\n", 2, "'repeat' is not closed"),
        ("program P\nwait 0\nend\n", 3, "'end' without"),
        ("program P\nroutine r\nend\n", 2, "modules only"),
        ("program P\nuse P\nwait 0\n", 2, "cannot use itself"),
        ("program P\nwait 0\nprogram Q\n", 3, "second header"),
        ("module M\nmove 0 0 0 0 0 0\n", 2, "outside a routine"),
        ("module M\nrepeat 2\nend\n", 2, "outside a routine"),
        ("module M\nroutine r\nend\nroutine r\nend\n", 4, "defined twice"),
        ("module M\nroutine r\nroutine s\nend\nend\n", 3, "must be at top level"),
        ("module M\nroutine r\ncall M.nope\nend\n", 3, "routine nope is not defined in M"),
    ],
)
def test_errors_name_line_and_reason(text: str, line: int, reason: str) -> None:
    with pytest.raises(ProgramError) as info:
        parse(text, LIMITS)
    assert info.value.line == line
    assert reason in info.value.reason
    assert str(info.value).startswith(f"line {line}: " if line else info.value.reason)


def test_limits_are_optional() -> None:
    assert parse("program P\nmove 999 0 0 0 0 0\n").instructions == (Move(2, (999.0, 0.0, 0, 0, 0, 0)),)


def test_expand_resolves_calls_speeds_loops_and_groups() -> None:
    tool = parse(MODULE, LIMITS)
    p = parse("program P\nuse Tool\nspeed 50\nrepeat 2\ncall Tool.twice\nend\nmove 1 1 1 1 1 1\n", LIMITS)
    steps = expand(p, {"Tool": tool})
    assert [s.kind for s in steps] == ["move", "wait"] * 4 + ["move"]
    # Speed set inside a routine stays inside; the caller's override applies afterwards.
    assert [s.speed for s in steps if s.kind == "move"] == [25.0] * 4 + [50.0]
    assert [s.origin for s in steps] == ["Tool"] * 8 + ["P"]
    assert [s.group for s in steps] == [1, 1, 1, 1, 2, 2, 2, 2, None]
    assert steps[-1].line == 7


def test_expand_reports_missing_module_and_routine() -> None:
    p = parse("program P\nuse Tool\ncall Tool.grip\ncall Tool.other\n", LIMITS)
    with pytest.raises(ProgramError, match="module Tool is not loaded") as info:
        expand(p, {})
    assert info.value.line == 3
    with pytest.raises(ProgramError, match="no routine other") as info:
        expand(p, {"Tool": parse(MODULE, LIMITS)})
    assert info.value.line == 4


def test_expand_stops_recursion_and_explosion() -> None:
    loop = parse("module L\nroutine r\ncall L.r\nend\n")
    with pytest.raises(ProgramError, match="nest deeper"):
        expand(parse("program P\nuse L\ncall L.r\n"), {"L": loop})
    big = "program P\nrepeat 10000\nrepeat 10000\nwait 0\nend\nend\n"
    with pytest.raises(ProgramError, match="more than"):
        expand(parse(big), {})


def test_samples_parse_within_the_simulated_arm_limits() -> None:
    files = samples()
    assert {"pick_and_place.robot", "palletize.robot", "gripper.robot"} <= set(files)
    parsed = {name: parse(text, LIMITS) for name, text in files.items()}
    modules = {p.name: p for p in parsed.values() if p.kind is Kind.MODULE}
    programs = [p for p in parsed.values() if p.kind is Kind.PROGRAM]
    assert len(programs) >= 2 and "Gripper" in modules
    for program in programs:
        assert program.uses == ("Gripper",)
        steps = expand(program, modules)
        assert len(steps) > 5 and any(s.origin == "Gripper" for s in steps)


def test_without_axes_a_move_is_refused_and_everything_else_parses():
    """Empty limits: the controller moves no motion device (configuration motion_device = "")."""
    with pytest.raises(ProgramError) as caught:
        parse("program P\nwait 1\nmove 0 0 0 0 0 0\n", [])
    assert caught.value.line == 3
    assert caught.value.reason == "'move' needs a motion device, and this controller moves none"
    program = parse("program P\nspeed 50\nrepeat 2\n  wait 0.5\nend\n", [])
    assert [type(i).__name__ for i in program.instructions] == ["Speed", "Repeat"]
