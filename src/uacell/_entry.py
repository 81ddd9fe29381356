"""The `uacell` command's entry point, kept tiny so that a stop request is caught from the start
(``uacell.core.early`` holds the handler and the flag it sets), and the compiled dataclass methods are
taken from their cache before anything defines one (``uacell.ua.codecache``)."""

from __future__ import annotations

from uacell.core import early
from uacell.ua import codecache


def run() -> int:
    import sys

    if "serve" in sys.argv[1:]:  # other commands keep Ctrl-C's usual meaning
        early.install_early_stop()
        early.pause_gc()
    codecache.install()
    try:
        from uacell.cli.main import main

        return main()
    except BaseException:
        # The stop may land anywhere, even inside an import that then fails with an error of its own.
        if early.stop_requested:
            return 0
        raise
