"""Where a leaked asyncio stream or socket was opened: a diagnostic for the suite.

A stream that no test closed is found by the garbage collector, often during a later, unrelated test,
and Python's own warning ("unclosed transport", "loop is closed") names neither the stream's test nor
its code. ``install()`` has every ``asyncio.StreamWriter`` note the test and the code that opened it;
a writer collected while still open then warns with both, beside Python's own warning (and, as every
warning in this suite, fails the test it surfaces in). Every ``socket.socket`` does the same: a plain
socket left open (a client library's own, no stream around it) names its test and code too.
"""

from __future__ import annotations

import _socket
import asyncio
import os
import socket
import traceback
import warnings
from typing import Any

_OPENED = "_uacell_opened_at"
_SOCKETS: dict[int, str] = {}  # id of an open socket -> where it was opened (sockets take no attributes)


def _site() -> str:
    test = os.environ.get("PYTEST_CURRENT_TEST", "outside any test")
    return f"{test}\n{''.join(traceback.format_stack(limit=10)[:-2])}"


def install() -> None:
    writer = asyncio.StreamWriter
    if getattr(writer, "_uacell_sites", False):
        return
    init, delete = writer.__init__, writer.__del__

    def __init__(self: asyncio.StreamWriter, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        test = os.environ.get("PYTEST_CURRENT_TEST", "outside any test")
        setattr(self, _OPENED, f"{test}\n{''.join(traceback.format_stack(limit=10)[:-1])}")

    def __del__(self: asyncio.StreamWriter) -> None:
        opened = getattr(self, _OPENED, None)
        transport = getattr(self, "_transport", None)
        try:  # the warning is an error in this suite: Python's own handling (it closes the stream) still runs
            if opened is not None and transport is not None and not transport.is_closing():
                warnings.warn(f"a stream nobody closed, opened in {opened}", ResourceWarning, stacklevel=1)
        finally:
            delete(self)

    writer.__init__ = __init__  # type: ignore[method-assign]
    writer.__del__ = __del__  # type: ignore[method-assign]
    writer._uacell_sites = True  # type: ignore[attr-defined]
    _install_sockets()


def _install_sockets() -> None:
    cls = socket.socket
    init = cls.__init__
    finalize = getattr(_socket.socket, "__del__")  # noqa: B009  # Python's own: warns and closes an open one (not in typeshed)

    def __init__(self: socket.socket, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        _SOCKETS[id(self)] = _site()

    def __del__(self: socket.socket) -> None:
        opened = _SOCKETS.pop(id(self), None)
        try:
            if opened is not None and self.fileno() != -1:
                warnings.warn(f"a socket nobody closed, opened in {opened}", ResourceWarning, stacklevel=1)
        finally:
            finalize(self)

    cls.__init__ = __init__  # type: ignore[method-assign]
    setattr(cls, "__del__", __del__)  # noqa: B010  # not in typeshed
