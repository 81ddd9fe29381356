"""``uacell config check [FILE]``: validate a configuration and show what it would serve, without serving."""

from __future__ import annotations

import re
from pathlib import Path

from uacell.config import Config, load_config, load_factory
from uacell.core.errors import ConfigError
from uacell.core.roles import Role, listening_policy


def equipment_specs(config: Config) -> list[tuple[str, str]]:
    """(table, "package.module:factory") of every factory the configuration names; the table as
    errors name it (``robot``, ``robots.Robot1.controllers.Controller1``)."""
    specs = [(name, getattr(settings, "equipment", "")) for name, settings in config.sections.items()]
    for key, section in config.cell.sections.items():
        for _, part in section.parts():
            stack = [(f"{key}.{part.name}", part)]
            while stack:
                path, p = stack.pop()
                spec = getattr(p.spec, "equipment", "")
                if spec:
                    specs.append((path, spec))
                # The folder is the key of the array of tables: Controllers -> controllers.
                stack.extend(
                    (".".join(x for x in (path, *map(_key, c.folder.split("/")), c.name) if x), c) for c in p.children
                )
    return [(where, spec) for where, spec in specs if spec]


def _key(folder: str) -> str:
    return re.sub(r"(?<=[a-z])(?=[A-Z])", "_", folder).lower()


def check_factories(config: Config) -> None:
    """Every factory the configuration names is importable and callable (it is called only when serving),
    and parts that share a connection to a PLC agree on its settings (``gateway.probe.shared_settings``)."""
    specs = equipment_specs(config)
    for where, spec in specs:
        try:
            load_factory(spec, where)
        except ConfigError as exc:
            raise ConfigError(f"configuration {config.source}: {exc}" if config.source else str(exc)) from exc
    if any(spec.startswith("uacell.gateway.") for _, spec in specs):
        from uacell.gateway.probe import shared_settings

        problems = shared_settings(config.cell.parts())
        if problems:
            raise ConfigError(f"cell {config.cell.source}: {problems[0]}")


def check_lines(config: Config) -> list[str]:
    """The report: where it came from, how it listens, which factories it loads, the parts."""
    cfg = config.server
    check_factories(config)
    anonymous = Role.parse(cfg.anonymous_role) if cfg.anonymous_role else None
    policy = listening_policy([cfg.host], anonymous, cfg.allow_none_security)
    lines = [
        f"configuration: {config.source or '(none: every default)'}",
        f"cell: {config.cell.source}",
        f"application: {cfg.application_name} ({cfg.application_uri})",
        f"endpoint: opc.tcp://{cfg.host}:{cfg.port}/",
        f"anonymous clients: {policy.anonymous_role.label}; SecurityPolicy None "
        + ("offered" if policy.none_security else "not offered"),
        f"data directory: {cfg.data_dir}",
        f"models: {cfg.models_dir or '(the per-user cache)'}",
        *(f"warning: {w}" for w in policy.warnings),
        "parts:",
        *(f"  {line}" for line in config.cell.describe(config.sections)),
    ]
    return lines


def run_check(path: Path | None, connect: bool = False) -> int:
    """Print what ``path`` would serve; ``connect``: also try every endpoint and tag of the gateway
    drivers the cell names (a table; exit status 1 when one is not as configured)."""
    config = load_config(path)
    for line in check_lines(config):
        print(line)
    print("configuration OK")
    if not connect:
        return 0
    import asyncio
    import logging

    from uacell.gateway.probe import probe, table

    for noisy in ("asyncua", "pymodbus"):  # the table says what they found
        logging.getLogger(noisy).setLevel(logging.ERROR)

    rows = asyncio.run(probe(config.cell.parts()))
    for line in table(rows):
        print(line)
    problems = sum(not r.ok for r in rows)
    print(f"connect: {len(rows) - problems} of {len(rows)} as configured" if rows else "")
    return 1 if problems else 0
