"""The models' own data types, kept beside the address-space snapshot so that a restart does not look
for them again.

asyncua encodes and decodes a structure or an enumeration that a model defines (PackML's
PackMLDescriptorDataType, Robotics' ExecutionModeEnumeration, ...) through a Python class made from
the type's DataTypeDefinition and registered in ``asyncua.ua``; a subtype of a built-in type (DI's
UpdateBehavior, a UInt32) is registered as an alias of its parent's class. Importing a NodeSet makes
and registers them as it goes. A server restored from a snapshot has not imported anything, so it
has to make them again; asyncua's ``load_data_type_definitions`` does, but it browses and reads every
DataType of the address space for it, the 500 of OPC UA's own included, each one loaded from the
snapshot: about a third of a restart's set-up.

What it would find depends only on the NodeSets (and asyncua's version), as the snapshot does. So
the writer of a snapshot describes what asyncua has registered for the models (``registered``: a
name, the type's NodeId and what the class is made from) and a restart makes and registers exactly
those (``register``), in the order asyncua registered them, which puts a type's field types before
it. A registration that cannot be described this way (a union, a class that is not what its
definition makes) leaves the description out, and the restart walks as before.
"""

from __future__ import annotations

import dataclasses
import logging
import pickle
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntFlag
from typing import Any

from asyncua import ua
from asyncua.common.structures104 import clean_name, make_enum, make_structure

log = logging.getLogger(__name__)

_DEFINITION = ua.AttributeIds.DataTypeDefinition
_PLAIN = (ua.StructureType.Structure, ua.StructureType.StructureWithOptionalFields)


@dataclass(frozen=True)
class Alias:
    """A subtype of a built-in type, decoded as its parent's class (``parent``)."""

    name: str
    data_type: ua.NodeId
    parent: type

    def known(self) -> bool:
        return hasattr(ua, self.name)  # asyncua's rule: an alias never replaces a class

    def register(self) -> None:
        ua.register_basetype(self.name, self.data_type, self.parent)


@dataclass(frozen=True)
class Enumeration:
    name: str
    data_type: ua.NodeId
    definition: ua.EnumDefinition
    option_set: bool

    def known(self) -> bool:
        return _known(self.name, self.data_type)

    def register(self) -> None:
        ua.register_enum(self.name, self.data_type, make_enum(self.name, self.definition, self.option_set)[self.name])


@dataclass(frozen=True)
class Structure:
    name: str
    data_type: ua.NodeId
    encoding: ua.NodeId  # the DefaultEncodingId its binary body is sent under
    definition: ua.StructureDefinition

    def known(self) -> bool:
        return _known(self.name, self.data_type)

    def register(self) -> None:
        made = make_structure(self.data_type, self.name, self.definition)
        if self.name not in made:
            raise ValueError(f"asyncua could not make the class of {self.name} ({self.data_type.to_string()})")
        ua.register_extension_object(self.name, self.encoding, made[self.name], self.data_type)


DataType = Alias | Enumeration | Structure


def _known(name: str, data_type: ua.NodeId) -> bool:
    """Registered already (by an earlier server in this process): asyncua keeps it, and so do we."""
    known: object = getattr(getattr(ua, name, None), "data_type", None)
    return isinstance(known, ua.NodeId) and known == data_type


def registered(nodes: Mapping[ua.NodeId, Any]) -> list[DataType] | None:
    """What asyncua has registered for the data types among ``nodes`` outside namespace 0: aliases,
    enumerations, structures, each in the order it registered them. None when one of them cannot be
    described so that ``register`` makes the same class again."""
    out: list[DataType] = []
    for data_type, name in list(ua.basetype_by_datatype.items()):
        if data_type.NamespaceIndex == 0 or data_type not in nodes:
            continue
        parent = getattr(ua, name, None)
        if not isinstance(parent, type) or not _by_reference(parent):
            return None
        out.append(Alias(name, data_type, parent))
    for data_type, cls in list(ua.enums_by_datatype.items()):
        if data_type.NamespaceIndex == 0 or data_type not in nodes:
            continue
        edef = _definition(nodes, data_type)
        option_set = issubclass(cls, IntFlag)
        members = {name: member.value for name, member in cls.__members__.items()}
        if not isinstance(edef, ua.EnumDefinition) or _members(edef, option_set) != members:
            return None
        out.append(Enumeration(cls.__name__, data_type, edef, option_set))
    for data_type, cls in list(ua.extension_objects_by_datatype.items()):
        if data_type.NamespaceIndex == 0 or data_type not in nodes:
            continue
        sdef = _definition(nodes, data_type)
        encoding = ua.typeid_by_extension_objects.get(cls)
        if not isinstance(sdef, ua.StructureDefinition) or encoding is None:
            return None
        fields = _fields(sdef)
        if fields is None or fields != _fields_of(cls):
            return None
        out.append(Structure(cls.__name__, data_type, encoding, sdef))
    return out


def register(entries: Iterable[DataType]) -> int:
    """Make and register each entry asyncua does not know yet; how many were made.

    Raises what asyncua raises for one it cannot make (the caller then walks for them instead)."""
    made = 0
    for entry in entries:
        if not entry.known():
            entry.register()
            made += 1
    return made


def stored(extras: Mapping[str, Any]) -> Sequence[DataType] | None:
    """The entries a snapshot's writer kept (``extras["data_types"]``), or None."""
    entries = extras.get("data_types")
    if not isinstance(entries, list) or not all(isinstance(e, Alias | Enumeration | Structure) for e in entries):
        return None
    return entries


def _definition(nodes: Mapping[ua.NodeId, Any], data_type: ua.NodeId) -> Any:
    value = nodes[data_type].attributes.get(_DEFINITION)
    return None if value is None or value.value is None or value.value.Value is None else value.value.Value.Value


def _members(edef: ua.EnumDefinition, option_set: bool) -> dict[str, int]:
    """The members ``make_enum`` makes of ``edef`` (when every field carries its value)."""
    return {clean_name(f.Name): (1 << f.Value if option_set else f.Value) for f in edef.Fields or ()}


def _fields(sdef: ua.StructureDefinition) -> list[str] | None:
    """The fields ``make_structure`` makes of a plain structure's definition; None for a union or
    a structure with subtyped values (not described)."""
    if sdef.StructureType not in _PLAIN:
        return None
    optional = ["Encoding"] if sdef.StructureType == ua.StructureType.StructureWithOptionalFields else []
    return optional + [clean_name(f.Name) for f in sdef.Fields or ()]


def _fields_of(cls: type) -> list[str] | None:
    return [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else None


def _by_reference(cls: type) -> bool:
    """A class pickle stores by its module and name (and so finds again)."""
    try:
        return pickle.loads(pickle.dumps(cls)) is cls
    except Exception:
        return False
