"""Start-up before the event loop: the early stop handler, the paused garbage collector, the loop.

Until the server's event loop takes over, SIGINT/SIGTERM end start-up quietly (exit 0, no
traceback): ``uacell._entry`` installs the handler before the heavy imports (asyncua and friends),
and ``uacell.cli.main`` reads ``stop_requested``. A leaf module: it imports nothing of uacell.
"""

from __future__ import annotations

import asyncio
import gc
import os
import signal
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")

stop_requested = False


class Stopped(Exception):
    """Raised by the early stop handler into whatever start-up was doing."""


def _stop_early(signum: int, frame: object) -> None:
    global stop_requested
    stop_requested = True
    raise Stopped


def install_early_stop() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _stop_early)


def pause_gc() -> None:
    """No cyclic garbage collection while the server starts.

    Start-up creates several hundred thousand long-lived objects (the address space); every few
    thousand allocations the collector would walk them all again, for nothing. ``resume_gc`` moves
    them out of its sight for good and turns it back on.
    """
    gc.disable()


def resume_gc() -> None:
    gc.freeze()
    gc.enable()


def event_loop_name() -> str:
    """The event loop ``run`` uses: ``uvloop`` where it is installed (Linux and macOS: a dependency
    there), else asyncio's own; ``UACELL_EVENT_LOOP=asyncio`` chooses asyncio's anyway."""
    if os.environ.get("UACELL_EVENT_LOOP", "").strip().lower() == "asyncio":
        return "asyncio"
    try:
        import uvloop  # noqa: F401
    except ImportError:
        return "asyncio"
    return "uvloop"


def run(main: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run`` on the loop ``event_loop_name`` names (uvloop's: about a quarter more requests
    a second through asyncua's TCP server here, docs/performance.md)."""
    if event_loop_name() == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    return asyncio.run(main)
