"""What the driver conformance tests share (docs/equipment.md, "Conformance"): the settings, the
factory and the time bound, from the environment. Each companion's tests are its own module:
``pytest --pyargs uacell.robotics.conformance`` and ``pytest --pyargs uacell.packml.conformance``.

``UACELL_SETTINGS`` is the part's ``settings`` table as TOML (what the server passes to the factory);
``UACELL_CONFORMANCE_TIMEOUT`` how many seconds an operation may take (default 60). A test whose
factory variable is not set is skipped.
"""

from __future__ import annotations

import asyncio
import os
import tomllib
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import pytest

T = TypeVar("T")
TASK = "TaskControl1"


def timeout() -> float:
    return float(os.environ.get("UACELL_CONFORMANCE_TIMEOUT", "60"))


def settings() -> dict[str, Any]:
    return tomllib.loads(os.environ.get("UACELL_SETTINGS", ""))


def factory(variable: str) -> str:
    factory = os.environ.get(variable, "")
    if not factory:
        pytest.skip(f"{variable} is not set")
    return factory


def run(make: Callable[[], Awaitable[T]]) -> T:
    async def bounded() -> T:
        return await asyncio.wait_for(make(), timeout())

    return asyncio.run(bounded())
