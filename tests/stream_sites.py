"""Where a leaked asyncio stream was opened: a diagnostic for the suite.

A stream that no test closed is found by the garbage collector, often during a later, unrelated test,
and Python's own warning ("unclosed transport", "loop is closed") names neither the stream's test nor
its code. ``install()`` has every ``asyncio.StreamWriter`` note the test and the code that opened it;
a writer collected while still open then warns with both, beside Python's own warning (and, as every
warning in this suite, fails the test it surfaces in).
"""

from __future__ import annotations

import asyncio
import os
import traceback
import warnings
from typing import Any

_OPENED = "_uacell_opened_at"


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
