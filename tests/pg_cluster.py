"""A real PostgreSQL cluster for tests: Debian's postgresql (``make setup`` installs it), initdb'd in
a temporary directory, listening on a free loopback port, started and stopped by the test (as the
``postgres`` user when run as root). Without it the tests that need one skip."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from helpers import free_port


def _pg_bin(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    for d in sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (d / name).exists():
            return str(d / name)
    return None


class PgCluster:
    """``initdb`` once; ``start`` and ``stop`` as often as a test needs (same port, same data)."""

    def __init__(self) -> None:
        initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
        if initdb is None or pg_ctl is None:
            pytest.skip("PostgreSQL is not installed (make setup installs Debian's postgresql)")
        pytest.importorskip("psycopg")
        self.pg_ctl = pg_ctl
        self.prefix: list[str] = []
        self.tmp = Path(tempfile.mkdtemp(prefix="uacell-pg-"))
        if os.geteuid() == 0:
            runuser = shutil.which("runuser")
            if runuser is None:
                pytest.skip("running as root without runuser: cannot start PostgreSQL as its own user")
            self.prefix = [runuser, "-u", "postgres", "--"]
            shutil.chown(self.tmp, "postgres")
        self.data, self.port = self.tmp / "data", free_port()
        try:
            subprocess.run([*self.prefix, initdb, "-D", str(self.data), "-A", "trust", "-U", "postgres"],
                           check=True, capture_output=True, timeout=120)  # fmt: skip
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
            shutil.rmtree(self.tmp, ignore_errors=True)
            pytest.skip(f"could not initialise PostgreSQL: {e}")

    @property
    def dsn(self) -> str:
        return f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres"

    def start(self) -> None:
        subprocess.run(
            [*self.prefix, self.pg_ctl, "-D", str(self.data), "-w", "-t", "60", "-l", str(self.tmp / "log"),
             "-o", f"-h 127.0.0.1 -p {self.port} -k {self.tmp}", "start"],
            check=True, capture_output=True, timeout=120,
        )  # fmt: skip

    def stop(self, mode: str = "fast") -> None:
        subprocess.run([*self.prefix, self.pg_ctl, "-D", str(self.data), "-m", mode, "-w", "stop"],
                       capture_output=True, timeout=120, check=False)  # fmt: skip

    def remove(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.tmp, ignore_errors=True)
