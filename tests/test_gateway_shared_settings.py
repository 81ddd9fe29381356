"""Parts on one Modbus/TCP endpoint share one connection, and a connection has one ``timeout``: two
parts that give it different timeouts are refused, naming both, by ``uacell config check`` and at
``uacell serve``'s start (before anything listens), instead of the second part's setting being
silently ignored."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import free_port

from uacell.core.cell_file import builtin_cell_path
from uacell.gateway.modbus import ModbusPool

SRC = str(Path(__file__).resolve().parents[1] / "src")
REFUSAL = (
    "Labeler: timeout = 2.5, but Capper shares its connection to modbus://127.0.0.1:5021 with timeout = 1: "
    "parts on one PLC endpoint use one connection, so give them the same timeout"
)


def uacell(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "uacell", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": SRC},
        check=False,
    )


def two_units(tmp_path: Path, labeler: str) -> Path:
    """The shipped two-unit cell (one PLC at 127.0.0.1:5021), the Labeler's equipment given ``labeler``."""
    path = tmp_path / "cell.toml"
    path.write_text(builtin_cell_path("modbus-packtags").read_text().replace("base = 100 }", f"base = 100{labeler} }}"))
    return path


async def test_the_pool_refuses_a_second_timeout_naming_both_parts() -> None:
    pool = ModbusPool()
    first = pool.connection("127.0.0.1", 5021, 1.0, part="Capper")
    assert pool.connection("127.0.0.1", 5021, 1.0, part="Labeler") is first and first.users == 2  # shared
    with pytest.raises(ValueError) as refused:
        pool.connection("127.0.0.1", 5021, 2.5, part="Labeler")
    assert str(refused.value) == REFUSAL
    assert first.users == 2 and first.timeout == 1.0  # nothing changed
    other = pool.connection("127.0.0.1", 5022, 2.5, part="Labeler")  # another endpoint: its own timeout
    assert other is not first and other.timeout == 2.5
    pool.close()


def test_config_check_refuses_parts_that_disagree_on_a_shared_connection(tmp_path: Path) -> None:
    proc = uacell("config", "check", str(two_units(tmp_path, ", timeout = 2.5")))
    assert proc.returncode != 0, proc.stdout
    errors = proc.stderr.strip().splitlines()
    assert len(errors) == 1 and errors[0].endswith(REFUSAL), proc.stderr
    assert "configuration OK" not in proc.stdout


def test_config_check_takes_parts_that_agree(tmp_path: Path) -> None:
    """Both set the same timeout (or leave the default): one connection, no complaint."""
    path = two_units(tmp_path, ", timeout = 1.0")
    proc = uacell("config", "check", str(path))
    assert proc.returncode == 0 and "configuration OK" in proc.stdout, proc.stdout + proc.stderr
    path.write_text(path.read_text().replace("unit = 1, base = 0 }", "unit = 1, base = 0, timeout = 1.0 }"))
    assert uacell("config", "check", str(path)).returncode == 0


def test_serve_refuses_them_before_it_listens(tmp_path: Path) -> None:
    port = free_port()
    proc = uacell(
        "--config", str(two_units(tmp_path, ", timeout = 2.5")),
        "serve", "--port", str(port), "--data-dir", str(tmp_path / "data"), "--no-web",
    )  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.strip().splitlines()[-1].endswith(REFUSAL), proc.stderr
    assert "Traceback" not in proc.stderr and "listening" not in proc.stdout


def test_a_robot_and_a_unit_on_one_plc_share_the_connection_and_its_timeout(tmp_path: Path) -> None:
    """The modbus-signals robot driver and the modbus-packtags units use the same pool."""
    robot = builtin_cell_path("modbus-robot").read_text().replace("port = 5020", "port = 5021, timeout = 2.0")
    path = tmp_path / "cell.toml"
    path.write_text(builtin_cell_path("modbus-packtags").read_text() + "\n" + robot)
    proc = uacell("config", "check", str(path))
    assert proc.returncode != 0, proc.stdout
    assert proc.stderr.strip().endswith(
        "Palletizer.Cabinet: timeout = 2, but Capper shares its connection to modbus://127.0.0.1:5021 with "
        "timeout = 1: parts on one PLC endpoint use one connection, so give them the same timeout"
    ), proc.stderr
    path.write_text(path.read_text().replace("port = 5021, timeout = 2.0", "port = 5022, timeout = 2.0"))
    assert uacell("config", "check", str(path)).returncode == 0  # another PLC: its own connection
