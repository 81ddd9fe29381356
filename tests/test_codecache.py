"""The compiled dataclass methods kept between starts (uacell.ua.codecache): each case in fresh
interpreters, as starts are."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from uacell.ua import codecache

ROOT = Path(__file__).resolve().parents[1]

# A start in miniature: install the cache, define dataclasses of every kind, report what was made.
_PROGRAM = """
import dataclasses, inspect, json, sys
from uacell.ua import codecache
cache = codecache.install()
from dataclasses import dataclass, field

@dataclass(frozen=True)
class Point:
    x: int
    y: float = 0.5
    tags: tuple[str, ...] = ()

@dataclass(order=True)
class Box:
    name: str
    items: list[int] = field(default_factory=list)
    point: Point = field(default_factory=lambda: Point(1))

a, b = Box("a", [1, 2]), Box("b")
try:
    Point(1).x = 2
    frozen = "changed"
except dataclasses.FrozenInstanceError as e:
    frozen = type(e).__name__
print(json.dumps({
    "installed": cache is not None,
    "compiled": cache.compiled if cache else None,
    "repr": [repr(a), repr(b), repr(Point(3, 1.5, ("t",)))],
    "eq": [Point(1) == Point(1), Point(1) == Point(2), a < b, hash(Point(1)) == hash(Point(1))],
    "frozen": frozen,
    "signatures": [str(inspect.signature(c)) for c in (Point, Box)],
    "annotations": [repr(c.__init__.__annotations__) for c in (Point, Box)],
    "code": [c.__init__.__code__.co_code.hex() for c in (Point, Box)],
}))
"""


def _start(cache_dir: Path | str) -> dict[str, object]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), codecache.ENV: str(cache_dir)}
    done = subprocess.run(
        [sys.executable, "-c", _PROGRAM], env=env, capture_output=True, text=True, timeout=60, check=True
    )
    result: dict[str, object] = json.loads(done.stdout)
    return result


def _file(cache_dir: Path) -> Path:
    return cache_dir / f"dataclasses.{sys.implementation.cache_tag}.marshal"


def _same_classes(a: dict[str, object], b: dict[str, object]) -> bool:
    keys = ("repr", "eq", "frozen", "signatures", "annotations", "code")
    return all(a[k] == b[k] for k in keys)


def test_the_next_start_compiles_no_method_and_makes_the_same_classes(tmp_path: Path) -> None:
    without = _start("off")
    assert without["installed"] is False
    first = _start(tmp_path)
    assert first["installed"] is True and isinstance(first["compiled"], int) and first["compiled"] > 0
    path = _file(tmp_path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600  # written at exit, the user's alone
    written = path.stat().st_mtime_ns
    second = _start(tmp_path)
    assert second["compiled"] == 0  # every method's code came from the file
    assert _same_classes(second, first) and _same_classes(second, without)
    assert path.stat().st_mtime_ns == written  # nothing new: not written again


@pytest.mark.parametrize(
    "spoil",
    [
        pytest.param(lambda p: p.write_bytes(b"\x00not marshal"), id="damaged"),
        pytest.param(lambda p: p.write_bytes(__import__("marshal").dumps([1, 2])), id="not-a-table"),
        pytest.param(lambda p: p.chmod(0o666), id="writable-by-others"),
    ],
)
def test_a_file_that_cannot_be_trusted_is_not_used_and_is_written_anew(tmp_path: Path, spoil) -> None:
    baseline = _start(tmp_path)
    path = _file(tmp_path)
    spoil(path)
    again = _start(tmp_path)
    assert again["compiled"] == baseline["compiled"]  # compiled as without a file
    assert _same_classes(again, baseline)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert _start(tmp_path)["compiled"] == 0  # the new file serves the next start


def test_a_text_compiled_with_future_flags_is_run_as_exec_would_run_it(tmp_path: Path) -> None:
    cache = codecache.CodeCache(str(tmp_path / "codes.marshal"))
    namespace: dict[str, object] = {}
    # this module has `from __future__ import annotations`: exec of a text inherits it
    cache.exec("def f(x: int) -> int: return x", {}, namespace)
    f = namespace["f"]
    assert f.__annotations__ == {"x": "int", "return": "int"}
    assert cache.compiled == 0 and cache.codes == {}  # passed through, not kept
