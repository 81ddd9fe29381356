"""uacell's optional extras (pyproject.toml, ``pip install 'uacell[modbus]'``): what each installs, and
the one-line error when the configuration needs one that is missing (README.md, "Install";
docs/configuration.md, "Optional extras").

The core server (the demo cell, the web HMI, SQLite history) needs none of them. A section or a driver
that does is refused by ``uacell config check`` and before ``uacell serve`` starts, in one line that
names the extra and the command that installs it; a module that imports an extra's library says the
same if it is imported without it (``MissingExtra.of``).
"""

from __future__ import annotations

import importlib.util

from uacell.core.errors import ConfigError

# extra -> the top-level modules it installs
EXTRAS: dict[str, tuple[str, ...]] = {
    "metrics": ("prometheus_client",),
    "postgres": ("psycopg",),
    "modbus": ("pymodbus",),
    "mqtt": ("aiomqtt",),
    "s7": ("snap7",),
    "logix": ("pylogix",),
    "sparkplug": ("aiomqtt", "google.protobuf"),
}


class MissingExtra(ConfigError):
    """``who`` (a section, a driver) needs ``extra``, which is not installed."""

    def __init__(self, who: str, extra: str) -> None:
        super().__init__(f"{who} needs the '{extra}' extra: pip install 'uacell[{extra}]'")
        self.who, self.extra = who, extra

    @classmethod
    def of(cls, who: str, exc: ImportError) -> ConfigError:
        """What to raise for ``exc``: a MissingExtra when an extra's module is what failed to import,
        else a ConfigError with ``exc``'s own message."""
        extra = providing(exc.name or "")
        return cls(who, extra) if extra else ConfigError(f"{who} cannot be loaded: {exc}")


def installed(module: str) -> bool:
    """``module`` can be imported (found, not blocked)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def providing(module: str) -> str | None:
    """The extra that installs ``module`` (or a module inside it), if any."""
    for extra, modules in EXTRAS.items():
        if any(module == m or module.startswith(m + ".") or m.startswith(module + ".") for m in modules):
            return extra
    return None


def require(extra: str, who: str) -> None:
    """MissingExtra unless every module ``extra`` installs can be imported."""
    if not all(installed(m) for m in EXTRAS[extra]):
        raise MissingExtra(who, extra)
