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


EVENT_LOOPS = ("auto", "uvloop", "asyncio")
EVENT_LOOP_ENV = "UACELL_EVENT_LOOP"


def uvloop_installed() -> bool:
    try:
        import uvloop  # noqa: F401
    except ImportError:
        return False
    return True


def event_loop_name(setting: str = "auto") -> str:
    """The event loop ``run`` uses for ``[server] event_loop`` (``$UACELL_EVENT_LOOP`` overrides it):
    ``auto`` is uvloop where it is installed (Linux and macOS: a dependency there), else asyncio's own;
    ``uvloop`` and ``asyncio`` name one (``uacell.config`` refuses ``uvloop`` where it is not installed)."""
    chosen = os.environ.get(EVENT_LOOP_ENV, "").strip().lower() or setting
    if chosen == "asyncio" or (chosen != "uvloop" and not uvloop_installed()):
        return "asyncio"
    return "uvloop"


def run(main: Coroutine[Any, Any, T], setting: str = "auto") -> T:
    """``asyncio.run`` on the loop ``event_loop_name(setting)`` names (uvloop's: about a quarter more
    requests a second through asyncua's TCP server here, docs/performance.md)."""
    if event_loop_name(setting) == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    return asyncio.run(main)
