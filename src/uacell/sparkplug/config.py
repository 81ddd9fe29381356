"""The ``[sparkplug]`` section (docs/configuration.md, docs/sparkplug.md).

The broker URL, keep-alive, TLS files and credentials are ``[pubsub]``'s keys with ``[pubsub]``'s
rules and code (``uacell.pubsub.config.BrokerConfig``): a password only from a file its owner alone
may read, or from ``$UACELL_SPARKPLUG_PASSWORD``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from uacell.core.errors import ConfigError
from uacell.core.roles import Role
from uacell.pubsub.config import BrokerConfig, check_broker
from uacell.pubsub.config import password_of as password_of  # the same rules, "[sparkplug]" in messages

PASSWORD_ENV = "UACELL_SPARKPLUG_PASSWORD"
# Sparkplug 3.0 (topic namespace elements): group, edge node and device ids are one topic level of
# UTF-8 without '/', '+', '#'.
_ID = re.compile(r"[^/+#\s]+")


@dataclass
class SparkplugConfig(BrokerConfig):
    """[sparkplug]: the cell as a Sparkplug B 3.0 edge node (docs/sparkplug.md); keep_alive: the broker
    sends the NDEATH after 1.5 of them."""

    section = "sparkplug"
    password_env = PASSWORD_ENV

    enabled: bool = False
    group_id: str = "uacell"
    edge_node_id: str = ""  # "": uacell-<host name>-<[server] port>
    client_id: str = ""  # "": <edge node id>-sparkplug (never [pubsub]'s, on the same broker)
    primary_host_id: str = ""  # "": no primary host: births as soon as connected
    command_role: str = ""  # the role DCMD method calls run under; "": every command refused
    parts: list[str] = field(default_factory=list)  # device ids (part paths) published; []: every one
    extra_values: list[str] = field(default_factory=list)  # "role:Browse/Path" added to a device's metrics
    axis_positions: bool = True  # a robot device carries its motion devices' axis positions


def check_sparkplug(cfg: SparkplugConfig) -> None:
    """Every [sparkplug] key that can be checked without the broker; ConfigError names the key."""
    check_broker(cfg)
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
    for entry in cfg.extra_values:
        role, _, path = entry.partition(":")
        if not role or not path:
            raise ConfigError(f"[sparkplug] extra_values: each entry is 'role:Browse/Path', not {entry!r}")
    for part in cfg.parts:
        if not _ID.fullmatch(part):
            raise ConfigError(f"[sparkplug] parts: each is a part's path such as 'Filler1', not {part!r}")
