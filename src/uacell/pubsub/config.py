"""The ``[pubsub]`` section (docs/configuration.md, docs/pubsub.md), and the broker keys it shares with
``[sparkplug]`` (``BrokerConfig``: the URL, keep-alive, TLS files and credentials, with their rules)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar
from urllib.parse import urlsplit

from uacell.core.errors import ConfigError
from uacell.core.secret_file import SecretError, read_secret

PASSWORD_ENV = "UACELL_MQTT_PASSWORD"
_TOPIC_LEVEL = re.compile(r"[^/+#\s]+")


@dataclass
class BrokerConfig:
    """The keys of a section whose MQTT client uacell keeps connected: [pubsub], [sparkplug]."""

    section: ClassVar[str] = "pubsub"  # in error messages: "[<section>] <key>: ..."
    password_env: ClassVar[str] = PASSWORD_ENV

    broker: str = "mqtt://127.0.0.1:1883"  # mqtt://host:port or mqtts://host:port (TLS)
    keep_alive: int = 10  # seconds: MQTT keep-alive ([pubsub]: also a silent writer's ua-keepalive)
    ca_file: Path | None = None  # mqtts: the CA that signed the broker's certificate ("": the system's)
    cert_file: Path | None = None  # mqtts: this client's certificate, when the broker asks for one
    key_file: Path | None = None  # ... and its private key
    username: str = ""
    password_file: Path | None = None  # a file only uacell's user may read; else $<password_env>


@dataclass
class PubSubConfig(BrokerConfig):
    """[pubsub]: the cell's values and events as OPC UA PubSub JSON over MQTT (docs/pubsub.md)."""

    enabled: bool = False
    client_id: str = ""  # "": the PublisherId
    publisher_id: str = ""  # "": uacell-<host name>-<[server] port>
    topic_prefix: str = "opcua"  # e.g. "umati/v3" (levels separated by "/")
    writer_group: str = "Cell"
    qos: int = 1  # 0, 1 or 2
    publishing_interval: float = 0.5  # seconds between DataSetMessages of a writer with changes
    positions_interval: float = 2.0  # seconds, for the robot axis positions writer
    axis_positions: bool = True  # publish each motion device's axis positions
    keyframe_count: int = 10  # every n-th message of a writer is a key frame (all fields)
    buffer: int = 10_000  # messages held while the broker is away; the oldest are dropped beyond it
    extra_values: list[str] = field(default_factory=list)  # "role:Browse/Path" added to a part's DataSet


@dataclass(frozen=True)
class Broker:
    host: str
    port: int
    tls: bool


def broker_of(cfg: BrokerConfig) -> Broker:
    """The broker ``cfg.broker`` names; ConfigError names the section's key."""
    url = urlsplit(cfg.broker)
    if url.scheme not in ("mqtt", "mqtts") or not url.hostname:
        raise ConfigError(
            f"[{cfg.section}] broker: must look like mqtt://host:1883 or mqtts://host:8883, not {cfg.broker!r}"
        )
    try:
        port = url.port
    except ValueError as exc:
        raise ConfigError(f"[{cfg.section}] broker: {exc}") from exc
    if url.username or url.password:
        raise ConfigError(f"[{cfg.section}] broker: no user or password in the URL (username, password_file)")
    tls = url.scheme == "mqtts"
    return Broker(url.hostname, port or (8883 if tls else 1883), tls)


def check_broker(cfg: BrokerConfig) -> None:
    """The broker keys that can be checked without the broker; ConfigError names the key."""
    broker_of(cfg)
    if not 5 <= cfg.keep_alive <= 3600:
        raise ConfigError(f"[{cfg.section}] keep_alive: must be 5..3600 seconds, not {cfg.keep_alive}")
    if cfg.key_file is not None and cfg.cert_file is None:
        raise ConfigError(f"[{cfg.section}] key_file: needs cert_file")


def check_pubsub(cfg: PubSubConfig) -> None:
    """Every [pubsub] key that can be checked without the broker; ConfigError names the key."""
    check_broker(cfg)
    for key in ("publisher_id", "writer_group", "client_id"):
        value = getattr(cfg, key)
        if value and not _TOPIC_LEVEL.fullmatch(value):
            raise ConfigError(f"[pubsub] {key}: must be one MQTT topic level (no '/', '+', '#' or space): {value!r}")
    levels = cfg.topic_prefix.split("/")
    if not all(_TOPIC_LEVEL.fullmatch(level) for level in levels):
        raise ConfigError(f"[pubsub] topic_prefix: topic levels without '+', '#' or space, not {cfg.topic_prefix!r}")
    if cfg.qos not in (0, 1, 2):
        raise ConfigError(f"[pubsub] qos: must be 0, 1 or 2, not {cfg.qos}")
    if not 0.01 <= cfg.publishing_interval <= 3600:
        raise ConfigError(f"[pubsub] publishing_interval: must be 0.01..3600 seconds, not {cfg.publishing_interval}")
    if not cfg.publishing_interval <= cfg.positions_interval <= 3600:
        raise ConfigError("[pubsub] positions_interval: must be publishing_interval..3600 seconds")
    for entry in cfg.extra_values:
        role, _, path = entry.partition(":")
        if not role or not path:
            raise ConfigError(f"[pubsub] extra_values: each entry is 'role:Browse/Path', not {entry!r}")


def password_of(cfg: BrokerConfig) -> str | None:
    """The broker password: from ``password_file`` (which only its owner may read), else the
    section's environment variable (``UACELL_MQTT_PASSWORD`` for [pubsub]), else none."""
    try:
        return read_secret(cfg.password_file, cfg.password_env, f"[{cfg.section}] password_file")
    except SecretError as exc:
        raise ConfigError(str(exc)) from None
