"""Start-up before the event loop: the early stop handler and the paused garbage collector.

Until the server's event loop takes over, SIGINT/SIGTERM end start-up quietly (exit 0, no
traceback): ``uacell._entry`` installs the handler before the heavy imports (asyncua and friends),
and ``uacell.cli`` reads ``stop_requested``. A leaf module: it imports nothing of uacell.
"""

from __future__ import annotations

import gc
import signal

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
