"""The optional extras (README.md, "Install"; docs/configuration.md, "Optional extras"): the core server
serves the demo cell without any of their libraries, and a section or a driver that needs a missing one
stops ``uacell config check`` and ``uacell serve`` with one line naming the extra and the pip command.

Every process here runs with the extras' libraries made unimportable: a ``sitecustomize`` on its
PYTHONPATH puts ``None`` in ``sys.modules`` for each, as if it were not installed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import start_serve
from helpers import free_port

from uacell.core.extras import EXTRAS, MissingExtra, providing, require

ROOT = Path(__file__).resolve().parents[1]
CELLS = ROOT / "src" / "uacell" / "cells"
# every library of every extra, and what they pull in that nothing else does
BLOCKED = sorted({m for modules in EXTRAS.values() for m in modules} | {"paho", "google.protobuf"})


@pytest.fixture(scope="module")
def blocked(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The environment of a process in which no extra is installed."""
    site = tmp_path_factory.mktemp("no-extras")
    (site / "sitecustomize.py").write_text(
        "import sys\n"
        f"for name in {BLOCKED!r}:\n"
        "    sys.modules[name] = None  # an import of it, or of anything inside it, fails\n"
    )
    path = os.pathsep.join([str(site), str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path}


def uacell(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "uacell", "--log-level", "WARNING", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )


def missing(who: str, extra: str) -> str:
    return f"{who} needs the '{extra}' extra: pip install 'uacell[{extra}]'"


def test_the_blocker_really_blocks(blocked: dict[str, str]) -> None:
    probe = "import importlib.util as u; import pymodbus"
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=blocked, timeout=60)
    assert proc.returncode == 1 and "ModuleNotFoundError" in proc.stderr


async def test_the_demo_cell_serves_without_any_extra(blocked: dict[str, str], tmp_path: Path) -> None:
    sp = start_serve(tmp_path / "data", env=blocked)
    try:
        async with Client(sp.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            state = await client.get_node(
                ua.NodeId("Filler1.BaseStateMachine.MachineState.CurrentState", ns)
            ).read_value()
            assert state.Text == "Stopped"
            status = await client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()
            assert status == ua.ServerState.Running
    finally:
        assert sp.stop() in (0, -15)
    assert not any("Traceback" in line or "needs the" in line for line in sp.output), "".join(sp.output)


SECTIONS = [
    ("[metrics]\nenabled = true\n", missing("[metrics]", "metrics")),
    (
        "[history]\nbackend = 'postgresql'\npostgresql_dsn = 'host=127.0.0.1 dbname=x'\n",
        missing("[history] backend = 'postgresql'", "postgres"),
    ),
    ("[pubsub]\nenabled = true\n", missing("[pubsub]", "mqtt")),
    ("[sparkplug]\nenabled = true\n", missing("[sparkplug]", "sparkplug")),
]
DRIVERS = [
    ("modbus-packtags.toml", "packml_units.Capper", "uacell.gateway.packml_modbus:modbus_packtags", "modbus"),
    ("s7-packtags.toml", "packml_units.Capper", "uacell.gateway.packml_s7:s7_packtags", "s7"),
    ("logix-packtags.toml", "packml_units.Capper", "uacell.gateway.packml_logix:logix_packtags", "logix"),
    ("modbus-robot.toml", "robots.Palletizer.controllers.Cabinet", "uacell.gateway.robot:modbus_signals", "modbus"),
    ("ur-robot.toml", "robots.UR5e.controllers.Cabinet", "uacell.gateway.ur_robot:ur_dashboard", "modbus"),
]
OPCUA_SIGNALS = """
[[robots]]
name = "Arm"
  [[robots.controllers]]
  name = "Cabinet"
  equipment = { driver = "opcua-signals", endpoint = "opc.tcp://127.0.0.1:4841/", prefix = "ns=1;s=Robot" }
"""


def test_config_check_names_the_missing_extra_in_one_line(blocked: dict[str, str], tmp_path: Path) -> None:
    cases: list[tuple[Path, str]] = []
    for i, (text, line) in enumerate(SECTIONS):
        path = tmp_path / f"section{i}.toml"
        path.write_text(text)
        cases.append((path, line))
    for file, where, spec, extra in DRIVERS:
        cases.append((CELLS / file, missing(f"[{where}] equipment: {spec!r}", extra)))
    with ThreadPoolExecutor(4) as pool:
        runs = list(pool.map(lambda case: uacell(blocked, "config", "check", str(case[0])), cases))
    for (path, line), proc in zip(cases, runs, strict=True):
        assert proc.returncode == 2, (path, proc.stdout, proc.stderr)
        assert proc.stderr.splitlines() == [f"uacell: configuration {path}: {line}"], (path, proc.stderr)
        assert "configuration OK" not in proc.stdout


def test_the_opcua_drivers_need_no_extra(blocked: dict[str, str], tmp_path: Path) -> None:
    signals = tmp_path / "opcua-signals.toml"
    signals.write_text(OPCUA_SIGNALS)
    with ThreadPoolExecutor(2) as pool:
        runs = list(
            pool.map(lambda p: uacell(blocked, "config", "check", str(p)), [CELLS / "packtags-unit.toml", signals])
        )
    for proc in runs:
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.splitlines()[-1] == "configuration OK"


@pytest.mark.parametrize("case", ["section", "driver"])
def test_serve_stops_at_start_with_the_same_line(blocked: dict[str, str], tmp_path: Path, case: str) -> None:
    if case == "section":
        path, line = tmp_path / "pubsub.toml", missing("[pubsub]", "mqtt")
        path.write_text(SECTIONS[2][0])
    else:
        path, line = CELLS / "s7-packtags.toml", missing(f"[packml_units.Capper] equipment: {DRIVERS[1][2]!r}", "s7")
    proc = uacell(
        blocked,
        "serve",
        "--config",
        str(path),
        "--port",
        str(free_port()),
        "--no-web",
        "--data-dir",
        str(tmp_path / "d"),
    )
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [f"uacell: configuration {path}: {line}"], proc.stderr
    assert "listening" not in proc.stdout


def test_each_extra_is_found_by_its_modules() -> None:
    assert providing("pymodbus.client") == "modbus"
    assert providing("google") == "sparkplug" and providing("google.protobuf.descriptor") == "sparkplug"
    assert providing("aiomqtt") == "mqtt" and providing("psycopg") == "postgres" and providing("asyncua") is None
    require("modbus", "[x]")  # installed here (make setup installs every extra)
    error = MissingExtra.of(
        "[metrics]", ModuleNotFoundError("No module named 'prometheus_client'", name="prometheus_client")
    )
    assert str(error) == missing("[metrics]", "metrics")
    other = MissingExtra.of("[x]", ModuleNotFoundError("No module named 'nope'", name="nope"))
    assert not isinstance(other, MissingExtra) and "cannot be loaded" in str(other)
