"""Secrets uacell reads at start (a broker's or a PLC's password): from a file only its owner may
read, else from an environment variable, never from a configuration file in clear text. A leaf
module: it imports nothing of uacell."""

from __future__ import annotations

import os
import stat
from pathlib import Path


class SecretError(ValueError):
    """A secret that cannot be used; the message is one line naming where it was looked for."""


def read_secret(path: Path | None, env: str, where: str) -> str | None:
    """The secret in ``path`` (refused when group or others may read it), else in the environment
    variable ``env``, else None. ``where`` names the setting in messages (``[pubsub] password_file``)."""
    if path is not None:
        try:
            mode = path.stat().st_mode
            if mode & (stat.S_IRWXG | stat.S_IRWXO):
                raise SecretError(f"{where}: {path} may be read by others (chmod 600 {path})")
            return path.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise SecretError(f"{where}: cannot read {path}: {exc.strerror or exc}") from exc
    return os.environ.get(env) or None
