"""docs/cookbook.md: every example runs against a served cell, and the page shows the files verbatim.

The examples are real files in docs/cookbook/ (asyncua and node-opcua). One `uacell serve` subprocess
serves a cell with the names the examples use (Robot1/Controller1/TaskControl1, Filler1) and a stop
mode configuration of its own, so the output shows what the server published, not the defaults.
"""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import INTEROP, ROOT, ServeProcess, start_serve

from uacell.security.users import UserStore

COOKBOOK = ROOT / "docs" / "cookbook"
PAGE = ROOT / "docs" / "cookbook.md"
USER, PASSWORD = "eve", "cookbook-engineer-1"
CELL = """
[robot]
time_scale = 20.0

[packml]
acting_time = 0.05

[[robots]]
name = "Robot1"

  [[robots.controllers]]
  name = "Controller1"
  possible_stop_modes = ["EndOfInstruction", "QuickStop", "OnPath"]
  default_stop_mode = "OnPath"

[[packml_units]]
name = "Filler1"
"""
# A program that runs until it is stopped; with comments enough for more than one 64 KiB Write.
LONG_PROGRAM = (
    "program Long version 1.0\n"
    + "".join(f"# comment line {i:05d} to make the file larger than one chunk\n" for i in range(1500))
    + "move 0 -30 20 0 60 0\nwait 600\n"
).encode()


def included_blocks(text: str) -> list[tuple[str, str]]:
    """(path, code) of each ``<!-- cookbook: PATH -->`` marker and the fenced block right after it."""
    pattern = re.compile(r"<!-- cookbook: (\S+) -->\n```[a-z]+\n(.*?)\n```\n", re.S)
    return [(m.group(1), m.group(2) + "\n") for m in pattern.finditer(text)]


def test_the_page_shows_every_example_file_once_and_verbatim():
    blocks = included_blocks(PAGE.read_text(encoding="utf-8"))
    assert PAGE.read_text(encoding="utf-8").count("<!-- cookbook:") == len(blocks), "a marker without its code block"
    files = sorted(str(p.relative_to(ROOT)) for p in COOKBOOK.iterdir() if p.suffix in (".py", ".js"))
    assert sorted(path for path, _ in blocks) == files
    for path, code in blocks:
        assert code == (ROOT / path).read_text(encoding="utf-8"), f"docs/cookbook.md shows an old {path}"


def test_readme_robotics_and_packml_link_the_cookbook():
    for doc in ("README.md", "docs/robotics.md", "docs/packml.md"):
        assert "cookbook.md" in (ROOT / doc).read_text(encoding="utf-8"), doc


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServeProcess]:
    tmp = tmp_path_factory.mktemp("cookbook")
    UserStore.in_data_dir(tmp / "data").add(USER, "engineer", PASSWORD)
    (tmp / "cell.toml").write_text(CELL, encoding="utf-8")
    sp = start_serve(tmp / "data", "--config", str(tmp / "cell.toml"))
    yield sp
    sp.stop()


def run(cmd: list[str], env: dict[str, str] | None = None) -> list[str]:
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=120, check=False, cwd=ROOT, env={**os.environ, **(env or {})}
    )
    assert proc.returncode == 0, f"{cmd} failed:\n{proc.stdout}\n{proc.stderr}"
    return [line for line in proc.stdout.splitlines() if line.strip()]


def python(example: str, *args: str) -> list[str]:
    return run([sys.executable, str(COOKBOOK / example), *args])


NODE_OPCUA_LOG = re.compile(r"\d\d:\d\d:\d\d\.\d+Z :")  # node-opcua's own log lines (on stdout)


def node(example: str, *args: str) -> list[str]:
    out = run(["node", str(COOKBOOK / example), *args], env={"NODE_PATH": str(INTEROP / "node_modules")})
    return [line for line in out if not NODE_OPCUA_LOG.match(line)]


def wait_for_rest(endpoint: str) -> None:
    """The robot powered down and the unit Stopped: where each example expects to begin."""

    async def states() -> None:
        async with Client(endpoint) as client:
            cell = await client.get_namespace_index("urn:uacell:cell")
            for path, state in (
                ("Robot1.Controllers.Controller1.SystemOperation.SystemOperationStateMachine", "Idle"),
                ("Filler1.BaseStateMachine.MachineState", "Stopped"),
            ):
                current = client.get_node(ua.NodeId(f"{path}.CurrentState", cell))
                async with asyncio.timeout(30):
                    while (await current.read_value()).Text != state:
                        await asyncio.sleep(0.05)

    asyncio.run(states())


def upload_and_replace(cell: ServeProcess, tmp_path: Path, example, name: str) -> None:
    stored = cell.data_dir / "programs" / "Robot1" / "Controller1" / name
    first = tmp_path / name
    first.write_bytes(b"program First\nwait 1\n")
    assert example(cell.endpoint, USER, PASSWORD, str(first)) == [f"uploaded {name}: 21 bytes"]
    assert stored.read_bytes() == b"program First\nwait 1\n"
    first.write_bytes(LONG_PROGRAM)  # the file exists now: replaced (Open with EraseExisting), in two chunks
    assert len(LONG_PROGRAM) > 64 * 1024
    assert example(cell.endpoint, USER, PASSWORD, str(first)) == [f"uploaded {name}: {len(LONG_PROGRAM)} bytes"]
    assert stored.read_bytes() == LONG_PROGRAM


RUN_OUTPUT = ["GetReady: 0", "LoadByName: 0", "Start: 0", "Stop: 0", "UnloadProgram: 0", "StandDown: 0"]


def test_asyncua_examples(cell: ServeProcess, tmp_path: Path):
    wait_for_rest(cell.endpoint)
    upload_and_replace(cell, tmp_path, lambda *a: python("upload_program.py", *a), "long_py.robot")
    out = python("run_program.py", cell.endpoint, "long_py")
    assert out == [
        "stop modes: {'EndOfInstruction': 5, 'QuickStop': 4, 'OnPath': 1} default: 1",
        *RUN_OUTPUT,
    ]
    wait_for_rest(cell.endpoint)
    assert python("packml_start.py", cell.endpoint) == [
        "Reset: Good",
        "Start: Good",
        "accepted: [[101, 'FillVolume', 250.5], [102, 'CapTorque', 2.25]]",
        "Stop: Good",
    ]
    assert python("lock.py", cell.endpoint) == [
        "InitLock: 0",
        "Locked: True",
        "LockingClient: urn:example.org:FreeOpcUa:opcua-asyncio",
        "ExitLock: 0",
        "Locked: False",
    ]


@pytest.mark.interop
def test_node_opcua_examples(cell: ServeProcess, tmp_path: Path):
    wait_for_rest(cell.endpoint)
    upload_and_replace(cell, tmp_path, lambda *a: node("upload_program.js", *a), "long_js.robot")
    out = node("run_program.js", cell.endpoint, "long_js")
    assert out == ['stop modes: {"EndOfInstruction":5,"QuickStop":4,"OnPath":1} default: 1', *RUN_OUTPUT]
    wait_for_rest(cell.endpoint)
    assert node("packml_start.js", cell.endpoint) == [
        "Reset: Good",
        "Start: Good",
        "accepted: [ [ 101, 'FillVolume', 250.5 ], [ 102, 'CapTorque', 2.25 ] ]",
        "Stop: Good",
    ]
    out = node("lock.js", cell.endpoint)
    assert out[:2] == ["InitLock: 0", "Locked: true"] and out[3:] == ["ExitLock: 0", "Locked: false"]
    assert re.fullmatch(r"LockingClient: urn:\S+:NodeOPCUA-Client", out[2])
