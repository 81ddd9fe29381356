"""``uacell config check [FILE]``: validate a configuration and show what it would serve, without serving."""

from __future__ import annotations

from pathlib import Path

from uacell.config import Config, load_config, load_factory
from uacell.roles import Role, listening_policy


def equipment_specs(config: Config) -> list[tuple[str, str]]:
    """(where, "package.module:factory") of every factory the configuration names."""
    specs = [(name, getattr(settings, "equipment", "")) for name, settings in config.sections.items()]
    for section in config.cell.sections.values():
        for _, part in section.parts():
            stack = [(part.name, part)]
            while stack:
                path, p = stack.pop()
                spec = getattr(p.spec, "equipment", "")
                if spec:
                    specs.append((path, spec))
                # The browse path, as NodeIds spell it: Robot1.Controllers.Controller1
                stack.extend((".".join(x for x in (path, *c.folder.split("/"), c.name) if x), c) for c in p.children)
    return [(where, spec) for where, spec in specs if spec]


def check_lines(config: Config) -> list[str]:
    """The report: where it came from, how it listens, which factories it loads, the parts."""
    cfg = config.server
    for where, spec in equipment_specs(config):
        load_factory(spec, where)  # importable and callable; it is called only when serving
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
        *(f"  {line}" for line in config.cell.describe()),
    ]
    return lines


def run_check(path: Path | None) -> int:
    for line in check_lines(load_config(path)):
        print(line)
    print("configuration OK")
    return 0
