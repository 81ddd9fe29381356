"""uacell's configuration: a TOML file, overridden by command-line options.

Every key is optional; without a file uacell serves the demo cell on 127.0.0.1:4840.

```toml
[server]
host = "127.0.0.1"
port = 4840
data_dir = "/var/lib/uacell"      # default: the per-user data directory
models_dir = "/opt/UA-Nodeset"    # default: the cache filled by 'uacell models fetch'
anonymous_role = "operator"       # default: operator on loopback, observer otherwise
allow_none_security = true        # default: only on loopback
trust_on_first_use = false
rejected_max_files = 100          # refused client certificates kept in pki/rejected/ (oldest dropped)
rejected_max_age_days = 30.0      # ... and for how long

[robot]
time_scale = 1.0                  # simulated robot: >1 runs faster than real time
equipment = ""                    # "package.module:factory" for real equipment (docs/equipment.md)

[packml]
acting_time = 1.0                 # seconds each acting state of the simulated unit takes
mach_speed = 60.0                 # initial MachSpeed, packages/min
equipment = ""                    # "package.module:factory" for real equipment (docs/equipment.md)

[web]                             # the browser HMI (docs/web.md)
enabled = true                    # 'uacell serve' runs it beside the server
host = "127.0.0.1"                # any non-loopback address is served over HTTPS only
port = 8080                       # 0: any free port (the listening line says which)
certificate = ""                  # PEM certificate for HTTPS (default: the server's certificate)
private_key = ""                  # its PEM private key (default: the server's key)
```
"""

from __future__ import annotations

import importlib
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import platformdirs

from uacell.errors import ConfigError

ROLES = ("observer", "operator", "engineer", "admin")


@dataclass
class ServerConfig:
    host: str = "127.0.0.1"
    port: int = 4840
    data_dir: Path = field(default_factory=lambda: Path(platformdirs.user_data_dir("uacell")))
    models_dir: str | None = None
    anonymous_role: str | None = None
    allow_none_security: bool | None = None
    trust_on_first_use: bool = False
    rejected_max_files: int = 100
    rejected_max_age_days: float = 30.0


@dataclass
class RobotConfig:
    time_scale: float = 1.0
    equipment: str = ""


@dataclass
class PackMLConfig:
    acting_time: float = 1.0
    mach_speed: float = 60.0
    equipment: str = ""


@dataclass
class WebConfig:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8080
    certificate: str = ""
    private_key: str = ""


@dataclass
class Config:
    server: ServerConfig = field(default_factory=ServerConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    packml: PackMLConfig = field(default_factory=PackMLConfig)
    web: WebConfig = field(default_factory=WebConfig)
    source: Path | None = None


_SECTIONS = {"server": ServerConfig, "robot": RobotConfig, "packml": PackMLConfig, "web": WebConfig}


def _coerce(section: str, key: str, value: object, default: object) -> object:
    name = f"[{section}] {key}"
    if key == "data_dir":
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be a path string")
        return Path(value).expanduser()
    if isinstance(default, bool) or key in ("allow_none_security",):
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false")
        return value
    if isinstance(default, int):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{name} must be an integer")
        return value
    if isinstance(default, float):
        if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
            raise ConfigError(f"{name} must be a positive number")
        return float(value)
    if not isinstance(value, str):
        raise ConfigError(f"{name} must be a string")
    if key == "anonymous_role" and value not in ROLES:
        raise ConfigError(f"{name} must be one of {', '.join(ROLES)}")
    return value


def load_config(path: str | Path | None = None) -> Config:
    """Read ``path`` (or return the defaults); raises ConfigError saying what is wrong and where."""
    config = Config()
    if path is None:
        return config
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read configuration {path}: {exc.strerror or exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"configuration {path} is not valid TOML: {exc}") from exc
    config.source = path
    for section, values in data.items():
        cls = _SECTIONS.get(section)
        if cls is None or not isinstance(values, dict):
            raise ConfigError(f"configuration {path}: unknown section [{section}]")
        target = getattr(config, section)
        known = {f.name for f in fields(cls)}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"configuration {path}: unknown key {key!r} in [{section}]")
            try:
                setattr(target, key, _coerce(section, key, value, getattr(target, key)))
            except ConfigError as exc:
                raise ConfigError(f"configuration {path}: {exc}") from exc
    for section in ("server", "web"):
        if not 0 <= getattr(config, section).port <= 65535:
            raise ConfigError(f"configuration {path}: [{section}] port must be 0..65535")
    if config.server.rejected_max_files < 1:
        raise ConfigError(f"configuration {path}: [server] rejected_max_files must be 1 or more")
    return config


def load_factory(spec: str, section: str) -> Callable[..., object]:
    """Import ``"package.module:name"`` named by ``[section] equipment``; ConfigError says what failed."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ConfigError(f"[{section}] equipment must look like 'package.module:factory', not {spec!r}")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"[{section}] equipment {spec!r} cannot be loaded: {exc}") from exc
    if not callable(factory):
        raise ConfigError(f"[{section}] equipment {spec!r} is not callable")
    return factory
