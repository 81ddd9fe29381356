"""The compiled methods of dataclasses, kept between starts.

Python makes a dataclass's ``__init__``, ``__repr__``, ``__eq__``, ... by writing their source and
compiling it, every time the class is defined: asyncua's protocol module defines about a thousand
of them, uacell some two hundred, and compiling their methods took 100 ms of every start here (a
third of a restart). The source of those methods is the same from one start to the next, so
``install`` gives the ``dataclasses`` module an ``exec`` that compiles each source text once and
keeps the code object by it in a per-user cache file; the next start runs the kept code instead of
compiling the same text again. ``exec`` of a code object compiled from a text is ``exec`` of that
text (same file name, same flags), so a class is made exactly as before; a text not in the cache is
compiled as before. Only ``dataclasses``' own lookups of ``exec`` are affected (a global of that
module, in front of the builtin).

The file is one ``marshal`` dict {source text: code object}, named by the interpreter's cache tag
(bytecode is version-specific, as ``.pyc`` files are); it is read at install, written (atomically,
owner-only) at exit when something was compiled, and ignored when it is unreadable, not owned by the
user or writable by others. ``UACELL_CODE_CACHE`` names another directory, ``off`` turns it off.
A leaf module (standard library only), installed by ``uacell._entry`` before anything heavy is
imported.
"""

from __future__ import annotations
import __future__

import atexit
import builtins
import contextlib
import marshal
import os
import stat
import sys
import types
from typing import Any

from uacell.ua import door

ENV = "UACELL_CODE_CACHE"
MAX_ENTRIES = 20_000  # beyond this the file starts afresh with what this run used

_exec = builtins.exec
# The compiler flags of ``from __future__`` imports, which ``exec`` of a text inherits from its caller.
_FUTURE_FLAGS = 0
for _feature in __future__.all_feature_names:
    _FUTURE_FLAGS |= getattr(__future__, _feature).compiler_flag


class CodeCache:
    """Code objects by source text, read from and written to ``path``."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.codes: dict[str, types.CodeType] = _read(path)
        self.used: set[str] = set()
        self.compiled = 0  # texts compiled in this run (not found in the file)

    def exec(self, source: Any, globals: Any = None, locals: Any = None, /) -> None:
        # a text compiled as ``exec`` would compile it for its caller: no future flags (dataclasses
        # has none; a caller with some is passed through)
        if type(source) is str and not sys._getframe(1).f_code.co_flags & _FUTURE_FLAGS:
            code = self.codes.get(source)
            if code is None:
                code = self.codes[source] = compile(source, "<string>", "exec", dont_inherit=True)
                self.compiled += 1
            self.used.add(source)
            source = code
        _exec(source, globals, locals)

    def save(self) -> None:
        """Write the file if this run compiled anything (atomically, owner-only); failures are quiet:
        it is a cache."""
        if not self.compiled:
            return
        codes = self.codes
        if len(codes) > MAX_ENTRIES:
            codes = {text: code for text, code in codes.items() if text in self.used}
        import tempfile  # at exit only: not an import every start pays

        directory = os.path.dirname(self.path)
        with contextlib.suppress(OSError, ValueError):
            os.makedirs(directory, mode=0o700, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".code-", suffix=".tmp", dir=directory)  # mode 0600
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(marshal.dumps(codes))
                os.replace(tmp, self.path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
            self.compiled = 0


def _read(path: str) -> dict[str, types.CodeType]:
    """The file's codes; nothing if it is missing, unreadable, damaged, or not the user's alone."""
    try:
        with open(path, "rb") as f:
            info = os.fstat(f.fileno())
            if info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                return {}
            data = marshal.loads(f.read())
    except (OSError, ValueError, EOFError, TypeError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {text: code for text, code in data.items() if type(text) is str and type(code) is types.CodeType}


def default_path() -> str | None:
    """``$UACELL_CODE_CACHE`` (``off``: none), else ``code`` in the per-user cache of uacell
    (``$XDG_CACHE_HOME/uacell``, ``~/.cache/uacell``)."""
    chosen = os.environ.get(ENV, "").strip()
    if chosen.lower() == "off":
        return None
    if not chosen:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        chosen = os.path.join(base, "uacell", "code")
    return os.path.join(chosen, f"dataclasses.{sys.implementation.cache_tag}.marshal")


_installed: CodeCache | None = None


def install(path: str | None = None) -> CodeCache | None:
    """Give ``dataclasses`` the caching ``exec`` (once per process) and save at exit; None when the
    cache is off or the interpreter has no cache tag."""
    global _installed
    if _installed is not None:
        return _installed
    path = path or default_path()
    if path is None or sys.implementation.cache_tag is None:
        return None
    cache = _installed = CodeCache(path)
    door.patch("dataclasses.exec", cache.exec)  # found before the builtin (the door's inventory lists it)
    atexit.register(cache.save)
    return cache
