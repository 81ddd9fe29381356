"""uacell's configuration: a TOML file, overridden by command-line options.

``[server]``, ``[programs]``, ``[limits]``, ``[web]``, ``[logging]``, ``[metrics]``, ``[users]`` and
``[discovery]`` are uacell's own; every other section belongs to a companion, which declares it
(``uacell.core.companion.Companion.section``/``settings``) in its package. Each section is a dataclass whose
fields are its keys, typed and defaulted; docs/configuration.md documents every one (type, default,
meaning), and tests/test_config_reference.py fails, naming the key, when the page and the dataclasses
disagree: a new key needs its row there.

Every key is optional; without a file uacell serves the demo cell on 127.0.0.1:4840. Every error is
one line, ``configuration FILE: [TABLE] KEY: message``.
"""

from __future__ import annotations

import importlib
import ipaddress
import os
import re
import socket
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, TypeVar

import platformdirs

from uacell.catalog import companions
from uacell.core.cell_file import CellConfig, SectionParser, builtin_cell_path, did_you_mean, parse_cell
from uacell.core.early import EVENT_LOOP_ENV, EVENT_LOOPS, uvloop_installed
from uacell.core.errors import ConfigError
from uacell.core.extras import MissingExtra, require
from uacell.core.roles import Role
from uacell.history.config import HistoryConfig
from uacell.pubsub.config import PubSubConfig, check_pubsub
from uacell.services.discovery_registration import DiscoveryConfig
from uacell.sparkplug.config import SparkplugConfig, check_sparkplug

T = TypeVar("T")

ROLES = tuple(role.label for role in Role)  # the role names, lowest first
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
LOG_FORMATS = ("text", "json")
CONFIG_ENV = "UACELL_CONFIG"
DATA_DIR_ENV = "UACELL_DATA_DIR"
CACHE_DIR_ENV = "UACELL_CACHE_DIR"


def _cell_sections() -> dict[str, SectionParser]:
    """Each companion's cell section (an array of tables, e.g. ``robots``) and its parser."""
    return {c.cell_section: c.cell_parser for c in companions() if c.cell_section and c.cell_parser}


def _env_path(name: str) -> Path | None:
    value = os.environ.get(name)
    return Path(value).expanduser() if value else None


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.-]", "-", socket.gethostname()) or "localhost"


def default_application_uri() -> str:
    """Unique per host (clients and certificates tell installations apart by it)."""
    return f"urn:{_host()}:uacell"


def default_application_name() -> str:
    return f"uacell@{_host()}"


MAX_SHUTDOWN_DELAY = 60.0  # a stop stays bounded (systemd's stop timeout is 90 s by default)


@dataclass
class ServerConfig:
    host: str = "127.0.0.1"
    port: int = 4840
    data_dir: Path = field(default_factory=lambda: Path(platformdirs.user_data_dir("uacell")))
    models_dir: str | None = None
    anonymous_role: str | None = None
    allow_none_security: bool | None = None
    trust_on_first_use: bool = False
    require_revocation_lists: bool = True  # every CA of a client's chain has its CRL in pki/crl/ (decision 92)
    application_uri: str = field(default_factory=default_application_uri)
    application_name: str = field(default_factory=default_application_name)
    rejected_max_files: int = 100
    rejected_max_age_days: float = 30.0
    address_space_cache: bool = True
    cache_dir: Path | None = field(default_factory=lambda: _env_path(CACHE_DIR_ENV))  # None: <data_dir>/cache
    snapshot_fork: bool = True  # the snapshot written by a forked child (else a thread): docs/configuration.md
    event_loop: str = "auto"  # auto (uvloop where installed), uvloop, asyncio; $UACELL_EVENT_LOOP overrides
    shutdown_delay: float = 2.0  # seconds a stop waits, ServerState Shutdown, for connected clients (decision 85)

    @property
    def snapshot_dir(self) -> Path | None:
        """Where the address-space snapshot lives; None when the cache is off."""
        if not self.address_space_cache:
            return None
        return self.cache_dir or self.data_dir / "cache"


@dataclass
class ProgramsConfig:
    """Bounds of one robot program (``uacell.robotics.program.ProgramLimits``) and of the folder."""

    max_file_bytes: int = 128 * 1024
    max_lines: int = 10_000
    max_nesting: int = 16
    max_steps: int = 20_000
    max_call_depth: int = 16
    max_work: int = 200_000
    max_folder_bytes: int = 64 * 1024 * 1024


def login_answer_margin(window: float) -> float:
    """Seconds a delayed login keeps before a deadline ``window`` seconds long: to check the password
    and send the answer back (decision 65)."""
    return min(5.0, window / 5)


@dataclass
class LimitsConfig:
    """What clients may hold and send (docs/security.md, "Limits")."""

    connections: int = 256  # TCP connections, before and after a session is activated
    sessions: int = 200
    subscriptions_per_session: int = 20
    subscriptions: int = 500
    monitored_items_per_subscription: int = 1000
    monitored_items: int = 20_000
    file_handles_per_session: int = 16
    file_handles: int = 128
    max_chunk_size: int = 65535  # the largest chunk (receive/send buffer) the server accepts
    max_message_size: int = 256 * 1024  # the largest request, all its chunks together
    pending_chunks_per_connection: int = 500  # chunks received but not yet processed, per connection
    pending_bytes_per_connection: int = 1024 * 1024  # the same in bytes
    operations_per_request: int = 1000  # nodes one Read/Write/Browse/Call/... may name
    login_base_delay: float = 1.0  # first delay after the free failures, doubled per further failure
    login_max_delay: float = 20.0  # at most activation_timeout - handshake_timeout - margin (decision 65)
    login_free_failures: int = 2  # failures in a row of one user name at one address without delay
    login_free_failures_per_user: int = 10  # the same over all addresses
    password_checks: int = 2  # password hashes verified at once, server-wide
    handshake_timeout: float = 5.0  # seconds from connecting to an open secure channel (Hello, OpenSecureChannel)
    activation_timeout: float = 30.0  # seconds from connecting to an activated session; closed beyond
    pending_per_address: int = 32  # connections of one address without an activated session


@dataclass
class WebConfig:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8080
    certificate: str = ""
    private_key: str = ""
    ua_sessions: int = 50
    release_after: float = 30.0
    header_timeout: float = 10.0


_POSITIVE = ("programs", "limits")  # sections whose every value must be above zero


@dataclass
class LoggingConfig:
    level: str = "INFO"
    format: str = "text"
    file: Path | None = None
    max_bytes: int = 10 * 1024 * 1024
    backups: int = 5
    audit: bool = True
    audit_file: Path | None = None  # None: <data_dir>/audit.log
    levels: dict[str, str] = field(default_factory=dict)


@dataclass
class MetricsConfig:
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 9840


@dataclass
class UsersConfig:
    min_password_length: int = 10
    certificate_grace: float = 0.0  # seconds a session keeps a certificate's user after it expires (decision 88)


# uacell's own sections (the companions declare theirs).
_OWN: dict[str, type[Any]] = {
    "server": ServerConfig,
    "programs": ProgramsConfig,
    "limits": LimitsConfig,
    "web": WebConfig,
    "logging": LoggingConfig,
    "metrics": MetricsConfig,
    "users": UsersConfig,
    "discovery": DiscoveryConfig,
    "history": HistoryConfig,
    "pubsub": PubSubConfig,
    "sparkplug": SparkplugConfig,
}
_PATHS = {"data_dir", "file", "audit_file", "cache_dir", "ca_file", "cert_file", "key_file", "password_file"}
_ZERO_MEANS_NO_BOUND = {"max_age_days", "max_mb"}  # [history]: 0 keeps history forever / unbounded


class Config:
    """uacell's own sections (``server``, ``programs``, ``limits``, ``web``, ``logging``, ``metrics``,
    ``users``, ``discovery``) plus one section per companion that declares one
    (``config.robot``, ``config.packml``)."""

    def __init__(self) -> None:
        self.server = ServerConfig()
        self.programs = ProgramsConfig()
        self.limits = LimitsConfig()
        self.web = WebConfig()
        self.logging = LoggingConfig()
        self.metrics = MetricsConfig()
        self.users = UsersConfig()
        self.discovery = DiscoveryConfig()
        self.history = HistoryConfig()
        self.pubsub = PubSubConfig()
        self.sparkplug = SparkplugConfig()
        self.source: Path | None = None
        # The cell: the companions' cell sections ([[robots]], [[packml_units]]), else the demo cell.
        self.cell: CellConfig = load_cell(builtin_cell_path("demo"))
        self.sections: dict[str, Any] = {
            c.section: c.settings() for c in companions() if c.section is not None and c.settings is not None
        }

    def section(self, name: str, kind: type[T]) -> T:
        """The section ``name``, typed: ``config.section("robot", RobotConfig)``."""
        value = self.sections[name]
        if not isinstance(value, kind):
            raise TypeError(f"[{name}] is a {type(value).__name__}, not a {kind.__name__}")
        return value

    def __getattr__(self, name: str) -> Any:
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(name)


def section_types() -> dict[str, type[Any]]:
    """Every settings section (``[server]``, ..., each companion's): its name and its dataclass.

    docs/configuration.md documents each field (tests/test_config_reference.py holds them together).
    """
    types: dict[str, type[Any]] = dict(_OWN)
    for c in companions():
        if c.section is not None and c.settings is not None:
            types[c.section] = c.settings
    return types


def _coerce(section: str, key: str, value: object, default: object) -> object:
    name = f"[{section}] {key}"
    if key in _PATHS:
        if not isinstance(value, str):
            raise ConfigError(f"{name}: must be a path string")
        return Path(value).expanduser() if value else None
    if key in ("extra_values", "parts"):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{name}: must be a list of strings")
        return list(value)
    if key == "capabilities":
        if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
            raise ConfigError(f"{name}: must be a list of capability identifiers (strings)")
        return list(value)
    if key == "levels":
        if not isinstance(value, dict) or not all(
            isinstance(k, str) and isinstance(v, str) and v.upper() in LOG_LEVELS for k, v in value.items()
        ):
            raise ConfigError(f"{name}: must map logger names to one of {', '.join(LOG_LEVELS)}")
        return {k: v.upper() for k, v in value.items()}
    if isinstance(default, bool) or key in ("allow_none_security",):
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: must be true or false")
        return value
    if isinstance(default, int):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{name}: must be an integer")
        if section in _POSITIVE and value < 1:
            raise ConfigError(f"{name}: must be a positive integer")
        return value
    if isinstance(default, float):
        if key in _ZERO_MEANS_NO_BOUND and isinstance(value, int | float) and not isinstance(value, bool):
            if value < 0:
                raise ConfigError(f"{name}: must be 0 (no bound) or more")
            return float(value)
        if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
            raise ConfigError(f"{name}: must be a positive number")
        return float(value)
    if not isinstance(value, str):
        raise ConfigError(f"{name}: must be a string")
    if key == "anonymous_role" and value not in ROLES:
        raise ConfigError(f"{name}: must be one of {', '.join(ROLES)}")
    if key == "level" and value.upper() not in LOG_LEVELS:
        raise ConfigError(f"{name}: must be one of {', '.join(LOG_LEVELS)}")
    if key == "event_loop":
        return check_event_loop(value, name)
    if key == "format" and value not in LOG_FORMATS:
        raise ConfigError(f"{name}: must be one of {', '.join(LOG_FORMATS)}")
    return value.upper() if key == "level" else value


def _read_toml(path: Path) -> dict[str, object]:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read configuration {path}: {exc.strerror or exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"configuration {path} is not valid TOML: {exc}") from exc


def load_cell(path: str | Path) -> CellConfig:
    """The cell sections of the TOML file ``path`` (the demo cell if it has none)."""
    path = Path(path)
    return _cell_of(_read_toml(path), path)


def _cell_of(data: dict[str, object], path: Path) -> CellConfig:
    sections = _cell_sections()
    if not any(key in data for key in sections):
        demo = builtin_cell_path("demo")
        if path != demo:
            return load_cell(demo)
    return parse_cell(data, str(path), sections)


def load_config(path: str | Path | None = None) -> Config:
    """Read ``path`` (or return the defaults); raises ConfigError saying what is wrong and where.

    Without ``path``, ``$UACELL_CONFIG`` names the file; ``$UACELL_DATA_DIR`` overrides ``data_dir``
    and ``$UACELL_CACHE_DIR`` overrides ``cache_dir``.
    """
    config = _load_file(path if path is not None else (os.environ.get(CONFIG_ENV) or None))
    env_data_dir = os.environ.get(DATA_DIR_ENV)
    if env_data_dir:
        config.server.data_dir = Path(env_data_dir).expanduser()
    env_cache_dir = os.environ.get(CACHE_DIR_ENV)
    if env_cache_dir:
        config.server.cache_dir = Path(env_cache_dir).expanduser()
    try:
        validate(config)
    except ConfigError as exc:
        raise ConfigError(f"configuration {config.source}: {exc}" if config.source else str(exc)) from exc
    return config


def _load_file(path: str | Path | None) -> Config:
    config = Config()
    if path is None:
        return config
    path = Path(path)
    data = _read_toml(path)
    config.source = path
    config.cell = _cell_of(data, path)
    for section, values in data.items():
        if section in _cell_sections():
            continue
        cls = section_types().get(section)
        if cls is None or not isinstance(values, dict):
            known_sections = [*section_types(), *(f"[{s}]" for s in _cell_sections())]
            raise ConfigError(
                f"configuration {path}: [{section}]: unknown section{did_you_mean(section, known_sections)}"
            )
        target = getattr(config, section) if section in _OWN else config.sections[section]
        known = [f.name for f in fields(cls)]
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"configuration {path}: [{section}] {key}: unknown key{did_you_mean(key, known)}")
            try:
                setattr(target, key, _coerce(section, key, value, getattr(target, key)))
            except ConfigError as exc:
                raise ConfigError(f"configuration {path}: {exc}") from exc
    if not 0 <= config.web.port <= 65535:
        raise ConfigError(f"configuration {path}: [web] port: must be 0..65535")
    most = max(1, config.limits.sessions // 2)
    web = data.get("web")
    if not (isinstance(web, dict) and "ua_sessions" in web):  # the default follows [limits] sessions
        config.web.ua_sessions = min(config.web.ua_sessions, most)
    if not 1 <= config.web.ua_sessions <= most:
        raise ConfigError(
            f"configuration {path}: [web] ua_sessions: must be 1..{most} (at most half of [limits] sessions), "
            f"not {config.web.ua_sessions}"
        )
    for key in ("application_uri", "application_name"):
        if not getattr(config.server, key).strip():
            raise ConfigError(f"configuration {path}: [server] {key}: must not be empty")
    limits = config.limits
    if not 8192 <= limits.max_chunk_size <= limits.max_message_size:
        raise ConfigError(f"configuration {path}: [limits] max_chunk_size: must be 8192..max_message_size")
    if limits.login_base_delay > limits.login_max_delay:
        raise ConfigError(f"configuration {path}: [limits] login_base_delay: must not exceed login_max_delay")
    margin = login_answer_margin(limits.activation_timeout)
    longest = limits.activation_timeout - margin - limits.handshake_timeout
    if limits.login_max_delay > longest:
        raise ConfigError(
            f"configuration {path}: [limits] login_max_delay: must be at most {longest:g} s: activation_timeout "
            f"({limits.activation_timeout:g} s) less handshake_timeout ({limits.handshake_timeout:g} s) and "
            f"{margin:g} s to check the password, so that a delayed login is answered before its connection is closed"
        )
    return config


# Validation: everything checked before anything is written ------------------------------------------------

_HOST_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def check_port(value: int, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        raise ConfigError(f"{name}: must be a TCP port 1..65535, not {value!r}")
    return value


def check_host(value: str, name: str) -> str:
    """An IP address or a DNS host name (RFC 1123); nothing is resolved here."""
    h = value.strip()
    bare = h[1:-1] if h.startswith("[") and h.endswith("]") else h
    try:
        ipaddress.ip_address(bare)
        return h
    except ValueError:
        pass
    labels = bare.rstrip(".").split(".")
    if not bare or len(bare) > 253 or not all(_HOST_LABEL.fullmatch(label) for label in labels):
        raise ConfigError(f"{name}: must be an IP address or host name, not {value!r}")
    return h


def check_event_loop(value: str, name: str) -> str:
    """``[server] event_loop`` (or ``$UACELL_EVENT_LOOP``): one of ``early.EVENT_LOOPS``, and uvloop only
    where it is installed."""
    chosen = value.strip().lower()
    if chosen not in EVENT_LOOPS:
        raise ConfigError(f"{name}: must be one of {', '.join(EVENT_LOOPS)}, not {value!r}")
    if chosen == "uvloop" and not uvloop_installed():
        raise ConfigError(f"{name}: uvloop is not installed: pip install uvloop, or choose auto or asyncio")
    return chosen


def check_directory(path: Path, name: str) -> Path:
    """``path`` is a directory, or can be made one: it is not a file, nor below a file."""
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir() and p == path:
                raise ConfigError(f"{name} {path} is not a directory")
            if not p.is_dir():
                raise ConfigError(f"cannot create {name} {path}: {p} is not a directory")
            if not os.access(p, os.W_OK | os.X_OK):
                raise ConfigError(f"cannot create {name} {path}: {p} is not writable")
            return path
    return path


def check_file(path: Path, name: str) -> Path:
    """``path`` can be written as a file: not a directory, and its directory can be made."""
    if path.is_dir():
        raise ConfigError(f"{name} {path} is a directory")
    check_directory(path.parent, f"the directory of {name}")
    return path


def validate(config: Config) -> None:
    """Raise ConfigError for the first value that cannot work; writes nothing."""
    check_port(config.server.port, "[server] port")
    check_host(config.server.host, "[server] host")
    check_host(config.web.host, "[web] host")
    check_event_loop(config.server.event_loop, "[server] event_loop")
    if env_loop := os.environ.get(EVENT_LOOP_ENV, "").strip():
        check_event_loop(env_loop, f"${EVENT_LOOP_ENV}")
    if config.server.rejected_max_files < 1:
        raise ConfigError("[server] rejected_max_files: must be 1 or more")
    if not 0.0 <= config.server.shutdown_delay <= MAX_SHUTDOWN_DELAY:
        raise ConfigError(f"[server] shutdown_delay: must be 0 to {MAX_SHUTDOWN_DELAY:g} seconds")
    check_directory(config.server.data_dir, "data directory")
    log = config.logging
    if log.file is not None:
        check_file(log.file, "log file")
    if log.audit_file is not None:
        check_file(log.audit_file, "audit file")
    if log.max_bytes < 1024:
        raise ConfigError(f"[logging] max_bytes: must be at least 1024, not {log.max_bytes}")
    if log.backups < 0:
        raise ConfigError(f"[logging] backups: must be 0 or more, not {log.backups}")
    check_port(config.metrics.port, "[metrics] port")
    check_host(config.metrics.host, "[metrics] host")
    url = config.discovery.url
    if url and not re.fullmatch(r"opc\.tcp://[^/\s]+(/\S*)?", url):
        raise ConfigError(f"[discovery] url: must look like opc.tcp://host:4840/, not {url!r}")
    if not 1 <= config.users.min_password_length <= 1024:
        raise ConfigError("[users] min_password_length: must be 1..1024")
    if not 0.0 <= config.users.certificate_grace <= 86400.0:
        raise ConfigError("[users] certificate_grace: must be 0 to 86400 seconds")
    check_history(config.history)
    check_pubsub(config.pubsub)
    check_sparkplug(config.sparkplug)
    check_extras(config)


def check_extras(config: Config) -> None:
    """MissingExtra (one line: the section, the extra, the pip command) for a section that is on and
    needs an optional extra that is not installed (README.md, "Install")."""
    needs = (
        (config.metrics.enabled, "metrics", "[metrics]"),
        (config.history.backend == "postgresql", "postgres", "[history] backend = 'postgresql'"),
        (config.pubsub.enabled, "mqtt", "[pubsub]"),
        (config.sparkplug.enabled, "sparkplug", "[sparkplug]"),
    )
    for on, extra, who in needs:
        if on:
            require(extra, who)


def check_history(h: HistoryConfig) -> None:
    if h.backend not in ("sqlite", "postgresql"):
        raise ConfigError(f"[history] backend: must be 'sqlite' or 'postgresql', not {h.backend!r}")
    if h.backend == "postgresql" and not h.postgresql_dsn.strip():
        raise ConfigError("[history] postgresql_dsn: needed with backend = 'postgresql'")
    if not 0.01 <= h.flush_interval <= 60:
        raise ConfigError(f"[history] flush_interval: must be 0.01..60 seconds, not {h.flush_interval}")
    if h.max_age_days < 0 or h.max_mb < 0:
        raise ConfigError("[history] max_age_days, max_mb: must be 0 (no bound) or more")
    if not 1 <= h.max_values_per_request <= 1_000_000:
        raise ConfigError("[history] max_values_per_request: must be 1..1000000")
    if not 1 <= h.max_events_per_request <= 100_000:
        raise ConfigError("[history] max_events_per_request: must be 1..100000")


def load_factory(spec: str, section: str) -> Callable[..., object]:
    """Import ``"package.module:name"`` named by ``[section] equipment``; ConfigError says what failed."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ConfigError(f"[{section}] equipment: must look like 'package.module:factory', not {spec!r}")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except ImportError as exc:  # a driver whose library is an extra not installed: one line naming it
        raise MissingExtra.of(f"[{section}] equipment: {spec!r}", exc) from exc
    except AttributeError as exc:
        raise ConfigError(f"[{section}] equipment: {spec!r} cannot be loaded: {exc}") from exc
    if not callable(factory):
        raise ConfigError(f"[{section}] equipment: {spec!r} is not callable")
    loaded: Callable[..., object] = factory
    return loaded
