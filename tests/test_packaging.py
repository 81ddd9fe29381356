"""The package builds without warnings (what `make setup` prints while installing uacell)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_package_builds_without_deprecation_warnings(tmp_path: Path) -> None:
    # A copy, so the build's own files stay out of the checkout.
    project = tmp_path / "project"
    shutil.copytree(ROOT / "src", project / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, project / name)
    # The build backend runs in an isolated environment, as in `make setup` (pip install -e .).
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--wheel-dir", str(tmp_path), "-v", str(project)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    output = proc.stdout + proc.stderr
    warnings = [line for line in output.splitlines() if "Deprecat" in line or "BuildBackendWarning" in line]
    assert warnings == [], "\n".join(warnings)
    assert len(list(tmp_path.glob("uacell-*.whl"))) == 1
