"""The driver conformance kit (``pytest --pyargs uacell.conformance``) passes the simulators and
fails a driver that breaks the Protocol, naming what is wrong."""

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


def _kit(tmp_path: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """Run the kit as a driver author would: from their own directory, with the factory in the environment."""
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--pyargs", "uacell.conformance"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(tmp_path), **env},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_the_simulated_robot_passes_the_robot_tests(tmp_path):
    proc = _kit(
        tmp_path,
        UACELL_ROBOT_FACTORY="uacell.robotics.sim:simulator",
        UACELL_SETTINGS="time_scale = 20.0",
        UACELL_AXES="7",
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "2 passed, 1 skipped" in proc.stdout


def test_the_simulated_unit_passes_the_unit_tests(tmp_path):
    proc = _kit(tmp_path, UACELL_UNIT_FACTORY="uacell.packml.sim:simulator", UACELL_SETTINGS="acting_time = 0.02")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "1 passed, 2 skipped" in proc.stdout


def test_a_driver_that_breaks_the_protocol_fails_with_the_reason(tmp_path):
    (tmp_path / "bad_driver.py").write_text(BAD_DRIVER)
    proc = _kit(tmp_path, UACELL_ROBOT_FACTORY="bad_driver:make")
    assert proc.returncode == 1
    assert "1 failed, 1 passed, 1 skipped" in proc.stdout
    assert "a CYCLE run to its end returns RunOutcome(pointer=3, completed=False)" in proc.stdout
