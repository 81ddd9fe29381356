"""The simulator as a process of its own, for tests (``python -m tests.ursim``, see server.py).

    with URSimProcess(programs_dir, dashboard_port, modbus_port, control_port) as robot:
        robot.control("estop")          # the control port (control.py)
        robot.kill()                    # the process itself killed (SIGKILL): nothing is answered

Every port is 127.0.0.1; the process is stopped on exit from the ``with`` block, also on failure.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path
from types import TracebackType

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 20.0


class URSimProcess:
    def __init__(self, programs_dir: Path, port: int, modbus_port: int, control_port: int, *options: str) -> None:
        """``options``: more command-line options, e.g. ``"--unlock-delay", "0"`` or ``"--local"``."""
        self.programs_dir, self.port, self.modbus_port, self.control_port = (
            programs_dir,
            port,
            modbus_port,
            control_port,
        )
        self.options = options
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        cmd = [sys.executable, "-m", "tests.ursim", "--port", str(self.port), "--programs-dir", str(self.programs_dir)]
        cmd += ["--modbus-port", str(self.modbus_port), "--control-port", str(self.control_port), *self.options]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # one line once every port listens (EOF if it could not start)
        if not line.startswith("ursim ready"):
            self.stop()
            raise RuntimeError(f"the UR simulator did not start: {line!r}")

    def control(self, command: str) -> str:
        """One command on the control port; its reply line."""
        with socket.create_connection(("127.0.0.1", self.control_port), timeout=TIMEOUT) as s:
            s.sendall((command + "\n").encode())
            return s.makefile().readline().strip()

    def kill(self) -> None:
        """The controller dies at once (SIGKILL): connections drop, no port answers."""
        if self.proc is not None:
            self.proc.kill()
            self._reap()

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            self._reap()

    def _reap(self) -> None:
        assert self.proc is not None
        self.proc.wait(TIMEOUT)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        self.proc = None

    def __enter__(self) -> URSimProcess:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
