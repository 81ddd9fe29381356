"""The driver conformance kits (``pytest --pyargs uacell.robotics.conformance`` and
``uacell.packml.conformance``) pass the simulators and fail a driver that breaks the Protocol, naming
what is wrong; without a factory they skip, saying which variable to set."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

BAD_DRIVER = textwrap.dedent(
    """
    from uacell.robotics.equipment import RunOutcome
    from uacell.robotics.sim import SimulatedRobot

    class NeverDone(SimulatedRobot):
        async def run(self, task, pointer, mode, progress):
            await super().run(task, pointer, mode, progress)
            return RunOutcome(3, completed=False)  # wrong: the program ran to its end

    def make(spec):
        return NeverDone(time_scale=0.02, axes=spec.axes)
    """
)


SRC = Path(__file__).resolve().parents[1] / "src"


def _kit(tmp_path: Path, kit: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run a kit as a driver author would: from their own directory, with the factory in the environment."""
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "--pyargs", kit],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{SRC}", **env},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_the_simulated_robot_passes_the_robot_tests(tmp_path):
    proc = _kit(
        tmp_path,
        "uacell.robotics.conformance",
        UACELL_ROBOT_FACTORY="uacell.robotics.sim:simulator",
        UACELL_SETTINGS="time_scale = 20.0",
        UACELL_AXES="7",
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "2 passed" in proc.stdout and "skipped" not in proc.stdout


def test_the_simulated_unit_passes_the_unit_tests(tmp_path):
    proc = _kit(
        tmp_path,
        "uacell.packml.conformance",
        UACELL_UNIT_FACTORY="uacell.packml.sim:simulator",
        UACELL_SETTINGS="acting_time = 0.02",
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "1 passed" in proc.stdout and "skipped" not in proc.stdout


def test_a_driver_that_breaks_the_protocol_fails_with_the_reason(tmp_path):
    (tmp_path / "bad_driver.py").write_text(BAD_DRIVER)
    proc = _kit(tmp_path, "uacell.robotics.conformance", UACELL_ROBOT_FACTORY="bad_driver:make")
    assert proc.returncode == 1
    assert "1 failed, 1 passed" in proc.stdout
    assert "a CYCLE run to its end returns RunOutcome(pointer=3, completed=False)" in proc.stdout


def test_without_a_factory_the_tests_skip_naming_the_variable(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("UACELL_ROBOT_FACTORY", "UACELL_UNIT_FACTORY")}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-rs",
            "-p",
            "no:cacheprovider",
            "--pyargs",
            "uacell.robotics.conformance",
        ],
        cwd=tmp_path,
        env={**env, "PYTHONPATH": str(SRC)},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert "2 skipped" in proc.stdout and "UACELL_ROBOT_FACTORY is not set" in proc.stdout
