"""The default PackTags map (ISA-TR88.00.02 tag names) under a prefix, every tag overridable.

Pure: it resolves tag names to addresses; nothing here talks to a PLC. A tag is either resolved
from the prefix or given in full by an override (any NodeId string, e.g. ``ns=3;i=1042``, or a
browse path). A prefix that is a NodeId string gives ``<prefix>.<path>`` (the string-NodeId
convention PLC PackML libraries use); a prefix that is a browse path from the Objects folder
(``/3:Capper/3:PackTags``) gives the tag's path below it, one browse name per dotted part, in the
namespace of the prefix's last element (``/3:Capper/3:PackTags/3:Command/3:CntrlCmd``); the gateway
translates browse paths into NodeIds when it connects.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

# tag key -> (path under the prefix, value type as the PLC keeps it)
DEFAULT_MAP: dict[str, tuple[str, str]] = {
    "Command.CntrlCmd": ("Command.CntrlCmd", "Int32"),
    "Command.CmdChangeRequest": ("Command.CmdChangeRequest", "Boolean"),
    "Command.UnitMode": ("Command.UnitMode", "Int32"),
    "Command.UnitModeChangeRequest": ("Command.UnitModeChangeRequest", "Boolean"),
    "Command.MachSpeed": ("Command.MachSpeed", "Float"),
    "Status.StateCurrent": ("Status.StateCurrent", "Int32"),
    "Status.UnitModeCurrent": ("Status.UnitModeCurrent", "Int32"),
    "Status.CurMachSpeed": ("Status.CurMachSpeed", "Float"),
    "Status.MachSpeed": ("Status.MachSpeed", "Float"),
    "Admin.ProdProcessedCount": ("Admin.ProdProcessedCount", "Int32"),
    "Admin.ProdDefectiveCount": ("Admin.ProdDefectiveCount", "Int32"),
    "Admin.StopReason": ("Admin.StopReason.ID", "Int32"),
}


# What needs which tags: a tag the PLC lacks refuses these (Bad_ConfigurationError, naming it); every
# other tag is optional (the unit works without it; docs/equipment.md, "Required and optional tags").
NEEDED_BY: dict[str, tuple[str, ...]] = {
    "every command": ("Status.StateCurrent", "Command.CntrlCmd", "Command.CmdChangeRequest"),
    "SetUnitMode": ("Status.UnitModeCurrent", "Command.UnitMode", "Command.UnitModeChangeRequest"),
    "SetMachSpeed": ("Command.MachSpeed",),
}


class PackTagsMapError(ValueError):
    """A map that cannot be resolved; the message is one line naming part and tag."""


@dataclass(frozen=True)
class ResolvedTag:
    key: str
    address: str  # a NodeId string or browse path (OPC UA); a Modbus point (packml_modbus.Point)
    type_name: str


@dataclass(frozen=True)
class Where:
    """Where a polled unit's PackTags are (``modbus-packtags``, ``s7-packtags``, ``logix-packtags``):
    the PLC, how it is polled, and every tag's address; ``rack`` and ``slot`` where the transport has them."""

    endpoint: str  # how messages name the PLC
    host: str
    port: int
    interval: float
    timeout: float
    tags: dict[str, ResolvedTag]
    rack: int = 0
    slot: int = 0


def resolve(
    part: str,
    prefix: str,
    overrides: Mapping[str, str] | None = None,
    parameters: int = 0,
    alarms: int = 0,
) -> dict[str, ResolvedTag]:
    """Every tag of the map as a NodeId string: the defaults under ``prefix``, then ``overrides``.

    ``parameters`` and ``alarms`` add ``Command.Parameter[i].Value`` and ``Admin.Alarm[i].ID``
    (0-based, as the PLC arrays are). An override key that is not a tag of the map is refused.
    """
    if not prefix and not overrides:
        raise PackTagsMapError(f"{part}: prefix: empty, and no tag is given in full")
    entries = dict(DEFAULT_MAP)
    for i in range(parameters):
        entries[f"Command.Parameter[{i}].Value"] = (f"Command.Parameter[{i}].Value", "Float")
    for i in range(alarms):
        entries[f"Admin.Alarm[{i}].ID"] = (f"Admin.Alarm[{i}].ID", "Int32")
    out = {k: ResolvedTag(k, _under(part, prefix, path) if prefix else "", t) for k, (path, t) in entries.items()}
    for key, node_id in (overrides or {}).items():
        if key not in out:
            raise PackTagsMapError(f"{part}: {key}: not a PackTags tag of the map")
        if not node_id.strip():
            raise PackTagsMapError(f"{part}: {key}: empty NodeId")
        out[key] = ResolvedTag(key, node_id, out[key].type_name)
    for key, tag in out.items():
        if not tag.address:
            raise PackTagsMapError(f"{part}: {key}: no prefix and no override")
    return out


def _under(part: str, prefix: str, path: str) -> str:
    """The address of ``path`` below ``prefix`` (module doc)."""
    if not prefix.startswith("/"):
        return f"{prefix}.{path}"
    last = prefix.rstrip("/").rsplit("/", 1)[-1]
    ns, colon, _name = last.partition(":")
    if not colon or not ns.isdigit():
        raise PackTagsMapError(f"{part}: prefix: {prefix!r}: each browse name is <namespace index>:<name>")
    return prefix.rstrip("/") + "".join(f"/{ns}:{name}" for name in path.split("."))
