"""The cell a configuration describes: reading and checking its tables, free of OPC UA.

Each companion declares its own section (``robots`` in ``uacell.robotics.config``, ``packml_units``
in ``uacell.packml.config``): a parser from the TOML array of tables to a ``CellSection``, which
knows its ``Part`` trees and how to describe itself. This module holds what they share: the
``Table`` reader (every error is one line naming the file, the table and the key), the rule for part
names, DI identification, and the checks across sections (a name used twice at the top level would
give two parts the same NodeIds).

Instance NodeIds are strings that follow the browse path (``Robot1.Controllers.Controller1``), so a
name must not contain the separator ``.`` nor characters a relative browse path reserves.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

from uacell.core.errors import ConfigError

# ASCII only (decision 34): names become NodeIds, file names (programs/<robot>/<controller>,
# packml/<unit>.json), metric labels and parts of the HMI's pages.
NAME_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]{0,63}$")
NAME_RULE = "an ASCII letter or '_' followed by up to 63 ASCII letters, digits, '_' or '-'"

# DI identification (ComponentType's optional members, on every DI device and component): key -> BrowseName.
IDENTIFICATION = {
    "manufacturer": "Manufacturer",
    "manufacturer_uri": "ManufacturerUri",
    "model": "Model",
    "product_code": "ProductCode",
    "serial_number": "SerialNumber",
    "product_instance_uri": "ProductInstanceUri",
    "hardware_revision": "HardwareRevision",
    "software_revision": "SoftwareRevision",
    "device_revision": "DeviceRevision",
    "device_manual": "DeviceManual",
    "device_class": "DeviceClass",
    "asset_id": "AssetId",
    "component_name": "ComponentName",
}

# What every state machine publishes (decision 1).
STATE_MACHINE = ("**/CurrentState/Number", "**/LastTransition/Number", "**/LastTransition/TransitionTime")


@dataclass
class Part:
    """An instance of ``type_name`` (in model ``model``) called ``name``, placed in ``folder``.

    ``folder`` is a BrowseName path below the parent part ("" = the parent itself); ``include`` lists
    the Optional members to create (see ``Selection``); ``children`` are parts placed below this one
    (typically in place of a placeholder).
    """

    name: str
    model: str
    type_name: str
    folder: str = ""
    include: tuple[str, ...] = ()
    children: list[Part] = field(default_factory=list)
    role: str = ""  # what the server binds to it: "controller", "task_control", "motion_device", "packml_unit"
    # Values of members (path -> text) written once at build, e.g. DI identification; their Optional
    # members are created. Not part of the tree's shape (not compared).
    values: dict[str, str] = field(default_factory=dict, compare=False)
    # The configuration the part came from (e.g. ``uacell.robotics.config.ControllerSpec``), for its binder.
    spec: object = field(default=None, compare=False)


class Table:
    """One TOML table being read: typed getters that fail with one line naming file, table and key.

    ``finish()`` rejects every key no getter asked for.
    """

    def __init__(self, data: object, where: str, source: str) -> None:
        self.where = where
        self.source = source
        if not isinstance(data, dict):
            raise self.error("", "must be a table")
        self.data: dict[str, Any] = data
        self.seen: set[str] = set()

    def error(self, key: str, message: str) -> ConfigError:
        what = f"[{self.where}] {key}" if key else f"[{self.where}]"
        return ConfigError(f"configuration {self.source}: {what}: {message}")

    def child(self, data: object, where: str) -> Table:
        return Table(data, f"{self.where}.{where}" if self.where else where, self.source)

    def entries(self, key: str, default: Sequence[dict[str, Any]] = ()) -> list[Table]:
        """The tables of the array ``key`` (``[[where.key]]``), each named ``key[N]`` by its position
        counted from 1, as a reader counts them in the file, until its ``name`` is read."""
        return [self.child(d, f"{key}[{i}]") for i, d in enumerate(self.tables(key, default), start=1)]

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str) -> Any:
        self.seen.add(key)
        return self.data.get(key)

    def string(self, key: str, default: str = "") -> str:
        value = self.raw(key)
        if value is None:
            return default
        if not isinstance(value, str):
            raise self.error(key, "must be a string")
        return value

    def number(self, key: str, default: float, *, minimum: float | None = 0.0, positive: bool = False) -> float:
        value = self.raw(key)
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, "must be a number")
        value = float(value)
        if positive and value <= 0:
            raise self.error(key, "must be greater than 0")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be at least {minimum:g}")
        return value

    def optional_number(self, key: str, *, positive: bool = False) -> float | None:
        if not self.has(key):
            self.seen.add(key)
            return None
        return self.number(key, 0.0, positive=positive)

    def integer(self, key: str, default: int) -> int:
        value = self.raw(key)
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, "must be an integer")
        return value

    def choice(self, key: str, options: Mapping[str, Any], default: str) -> Any:
        text = self.string(key, default)
        if text not in options:
            raise self.error(key, f"{text!r} is not one of {', '.join(options)}")
        return options[text]

    def name(self, key: str = "name", default: str | None = None) -> str:
        if not self.has(key) and default is not None:
            self.seen.add(key)
            return default
        if not self.has(key):
            typo = difflib.get_close_matches(key, [k for k in self.data if isinstance(k, str)], n=1, cutoff=0.75)
            hint = f"; is {typo[0]!r} meant to be {key!r}?" if typo else ""
            raise self.error(key, f"is missing (every part needs a name){hint}")
        value = self.string(key)
        check_name(value, lambda message: self.error(key, message))
        if key == "name" and self.where.endswith("]"):
            # From here on errors name the table by the part's name: [robots.Robot1.controllers.C1].
            self.where = f"{self.where[: self.where.rindex('[')]}.{value}"
        return value

    def table(self, key: str) -> Table:
        value = self.raw(key)
        return self.child({} if value is None else value, key)

    def free_table(self, key: str) -> dict[str, Any]:
        """A table whose keys are not checked here (settings for an equipment factory)."""
        value = self.raw(key)
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(key, "must be a table")
        return dict(value)

    def equipment(self, drivers: Mapping[str, str]) -> tuple[str, dict[str, Any]]:
        """The part's equipment: ``equipment = "package.module:factory"`` with its ``settings`` table, or
        ``equipment = { driver = "modbus-signals", host = ..., ... }``: one of the ``drivers`` shipped for
        this kind of part (name -> factory), the other keys its settings (``settings`` may add more,
        not repeat them)."""
        value = self.raw("equipment")
        settings = self.free_table("settings")
        if value is None or isinstance(value, str):
            return value or "", settings
        if not isinstance(value, dict):
            raise self.error("equipment", "must be 'package.module:factory' or a table with a driver")
        options = dict(value)
        driver = options.pop("driver", None)
        if driver not in drivers:
            known = ", ".join(sorted(drivers)) or "none is shipped for this part yet"
            message = f"driver {driver!r} is not one of: {known}" if driver else f"needs a driver ({known})"
            raise self.error("equipment", message)
        twice = sorted(set(options) & set(settings))
        if twice:
            raise self.error("settings", f"{twice[0]!r} is given in equipment already")
        return drivers[driver], {**options, **settings}

    def tables(self, key: str, default: Sequence[dict[str, Any]] = ()) -> list[dict[str, Any]]:
        """An array of tables (``[[where.key]]``)."""
        value = self.raw(key)
        if value is None:
            return [dict(d) for d in default]
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self.error(key, "must be an array of tables")
        return value

    def finish(self) -> None:
        for key in self.data:
            if key not in self.seen:
                raise self.error(key, "unknown key" + did_you_mean(key, sorted(self.seen)))


def did_you_mean(word: str, known: Sequence[str]) -> str:
    """``"; did you mean 'x'?"`` for the nearest of ``known`` (a typo), else ``""``."""
    close = difflib.get_close_matches(word, known, n=1, cutoff=0.75)
    return f"; did you mean {close[0]!r}?" if close else ""


def check_name(name: str, fail: Callable[[str], ConfigError]) -> None:
    if not NAME_PATTERN.match(name):
        other = next((c for c in name if not c.isascii()), None)
        why = f" ({other!r} is not ASCII)" if other is not None else " (NodeIds join names with '.')"
        raise fail(f"{name!r} cannot be a BrowseName here: use {NAME_RULE}{why}")


def unique(names: Sequence[tuple[str, Table]], what: str, key: str = "name") -> None:
    """Two parts in one place may not share a name (they would share BrowseName and NodeIds)."""
    seen: set[str] = set()
    for name, table in names:
        if name in seen:
            raise table.error(key, f"{what} {name!r} is declared twice")
        seen.add(name)


def read_identification(table: Table) -> dict[str, str]:
    """``identification = { manufacturer = "...", ... }``: BrowseName -> text."""
    ident = table.table("identification")
    values = {member: ident.string(key) for key, member in IDENTIFICATION.items() if ident.has(key)}
    ident.finish()
    return values


def identification_lines(values: Mapping[str, str]) -> list[str]:
    return [f"{k} = {v!r}" for k, v in values.items()]


class CellSection(Protocol):
    """What a companion's cell section offers the server and ``uacell config check``."""

    def parts(self) -> list[tuple[str, Any]]:
        """``(root, Part)`` pairs (roots: ``DeviceSet``, ``PackMLObjects``)."""
        ...

    def top_names(self) -> list[tuple[str, Table]]:
        """The names directly below a root (they start NodeIds, so they must be unique cell-wide)."""
        ...

    def describe(self, settings: Mapping[str, Any]) -> list[str]:
        """Lines of the tree, indented by two spaces per level, with the values in effect: ``settings``
        are the configuration's sections by name (the defaults a part does not override)."""
        ...


SectionParser = Callable[[Table, str], CellSection]


@dataclass
class CellConfig:
    """The parts of the cell, by section (``robots``, ``packml_units``); ``source`` names where they came from."""

    sections: dict[str, CellSection] = field(default_factory=dict)
    source: str = ""

    def parts(self) -> list[tuple[str, Any]]:
        return [p for s in self.sections.values() for p in s.parts()]

    def describe(self, settings: Mapping[str, Any]) -> Iterator[str]:
        for section in self.sections.values():
            yield from section.describe(settings)


def parse_cell(data: Mapping[str, Any], source: str, parsers: Mapping[str, SectionParser]) -> CellConfig:
    """The cell sections of a parsed TOML document (other sections are left to the caller)."""
    root = Table(dict(data), "", source)
    cell = CellConfig(source=source)
    for key in data:  # in the order the file gives them
        if key in parsers:
            cell.sections[key] = parsers[key](root, key)
    # Robots and units start NodeIds alike: one name may not be used twice across the sections.
    first: dict[str, Table] = {}
    for name, table in (n for s in cell.sections.values() for n in s.top_names()):
        other = first.setdefault(name, table)
        if other is not table:
            kind = other.where.split(".", 1)[0]
            raise table.error(
                "name",
                f"{name!r} is declared twice: the [[{kind}]] entry [{other.where}] has that name already"
                " (the parts at the top of the cell share one set of names: they start NodeIds)",
            )
    return cell


def builtin_cell_path(name: str) -> Path:
    """The shipped cell ``demo`` (the default), ``example`` (a larger cell), ``modbus-robot`` (a
    robot behind Modbus/TCP signals), ``packtags-unit`` (a PackML unit in a PLC over OPC UA) or
    ``modbus-packtags`` (two units in a PLC over Modbus/TCP) or ``s7-packtags`` (two units in a
    Siemens S7 data block) or ``logix-packtags`` (a unit in a Rockwell Logix controller; docs/equipment.md)."""
    return Path(str(resources.files("uacell") / "cells" / f"{name}.toml"))
