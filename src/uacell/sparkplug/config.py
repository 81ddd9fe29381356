"""The ``[sparkplug]`` section (docs/configuration.md, docs/sparkplug.md).

The broker URL, TLS files and credentials follow ``[pubsub]``'s rules with ``[pubsub]``'s own code
(``uacell.pubsub.config.broker_of``, ``uacell.secret_file``): a password only from a file its owner
alone may read, or from ``$UACELL_SPARKPLUG_PASSWORD``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from uacell.errors import ConfigError
from uacell.pubsub.config import Broker, PubSubConfig, broker_of
from uacell.roles import Role
from uacell.secret_file import SecretError, read_secret

PASSWORD_ENV = "UACELL_SPARKPLUG_PASSWORD"
# Sparkplug 3.0 (topic namespace elements): group, edge node and device ids are one topic level of
# UTF-8 without '/', '+', '#'.
_ID = re.compile(r"[^/+#\s]+")


@dataclass
class SparkplugConfig:
    """[sparkplug]: the cell as a Sparkplug B 3.0 edge node (docs/sparkplug.md)."""

    enabled: bool = False
    broker: str = "mqtt://127.0.0.1:1883"  # mqtt://host:port or mqtts://host:port (TLS)
    group_id: str = "uacell"
    edge_node_id: str = ""  # "": uacell-<host name>-<[server] port>
    client_id: str = ""  # "": <edge node id>-sparkplug (never [pubsub]'s, on the same broker)
    primary_host_id: str = ""  # "": no primary host: births as soon as connected
    command_role: str = ""  # the role DCMD method calls run under; "": every command refused
    parts: list[str] = field(default_factory=list)  # device ids (part paths) published; []: every one
    extra_values: list[str] = field(default_factory=list)  # "role:Browse/Path" added to a device's metrics
    axis_positions: bool = True  # a robot device carries its motion devices' axis positions
    keep_alive: int = 10  # seconds: MQTT keep-alive (the broker sends NDEATH after 1.5 of them)
    ca_file: Path | None = None  # mqtts: the CA that signed the broker's certificate ("": the system's)
    cert_file: Path | None = None  # mqtts: this client's certificate, when the broker asks for one
    key_file: Path | None = None  # ... and its private key
    username: str = ""
    password_file: Path | None = None  # a file only uacell's user may read; else $UACELL_SPARKPLUG_PASSWORD


def broker_of_sparkplug(cfg: SparkplugConfig) -> Broker:
    """The broker ``[sparkplug] broker`` names, checked as ``[pubsub] broker`` is."""
    try:
        return broker_of(PubSubConfig(broker=cfg.broker))
    except ConfigError as exc:
        raise ConfigError(str(exc).replace("[pubsub]", "[sparkplug]")) from None


def check_sparkplug(cfg: SparkplugConfig) -> None:
    """Every [sparkplug] key that can be checked without the broker; ConfigError names the key."""
    broker_of_sparkplug(cfg)
    for key in ("group_id", "edge_node_id", "client_id", "primary_host_id"):
        value = getattr(cfg, key)
        if (value or key == "group_id") and not _ID.fullmatch(value):
            raise ConfigError(f"[sparkplug] {key}: must be one MQTT topic level (no '/', '+', '#' or space): {value!r}")
    if cfg.command_role:
        try:
            Role.parse(cfg.command_role)
        except ValueError:
            names = ", ".join(r.label for r in Role)
            raise ConfigError(
                f"[sparkplug] command_role: must be one of {names} (or empty), not {cfg.command_role!r}"
            ) from None
    if not 5 <= cfg.keep_alive <= 3600:
        raise ConfigError(f"[sparkplug] keep_alive: must be 5..3600 seconds, not {cfg.keep_alive}")
    if cfg.key_file is not None and cfg.cert_file is None:
        raise ConfigError("[sparkplug] key_file: needs cert_file")
    for entry in cfg.extra_values:
        role, _, path = entry.partition(":")
        if not role or not path:
            raise ConfigError(f"[sparkplug] extra_values: each entry is 'role:Browse/Path', not {entry!r}")
    for part in cfg.parts:
        if not _ID.fullmatch(part):
            raise ConfigError(f"[sparkplug] parts: each is a part's path such as 'Filler1', not {part!r}")


def password_of(cfg: SparkplugConfig) -> str | None:
    """The broker password: from ``password_file`` (which only its owner may read), else
    ``$UACELL_SPARKPLUG_PASSWORD``, else none."""
    try:
        return read_secret(cfg.password_file, PASSWORD_ENV, "[sparkplug] password_file")
    except SecretError as exc:
        raise ConfigError(str(exc)) from None
