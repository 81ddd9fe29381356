"""Command metrics: a DCMD that writes one runs the method call it names through the server's one
method dispatcher, as an OPC UA client's call would (argument checks, the role table, DI locks,
serialization per state machine, the audit trail), under ``[sparkplug] command_role``.

Declared by the companions with their parts' DataSets (``uacell.core.datasets.PartDataSet.commands``): the
metric's name and the method(s) it calls, as (object path below the part, method BrowseName); where
one name stands for several methods (PackML's Reset), the first whose Executable is true is called,
else the first. A method without inputs is a Boolean metric (writing true calls it); a method with
one scalar input takes the metric's value as it; a method whose one input is an array of descriptor
structures (ID, Name, Value: PackML's Start) is a Boolean metric whose array comes from the
``<command>/Parameter/<ID>`` metrics of the same DCMD (docs/sparkplug.md, "Commands").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from asyncua import ua

from uacell.binding.dispatch import BoundMethod
from uacell.core.datasets import Command as DeclaredCommand
from uacell.sparkplug.payload import DataType
from uacell.sparkplug.values import VARIANTS, datatype_of

Builtin = Callable[[ua.NodeId], ua.VariantType | None]

PREFIX = "Command/"
RESULT_COMMAND = "Command/Result/Command"
RESULT_CODE = "Command/Result/StatusCode"
RESULT_SYMBOL = "Command/Result/Symbol"
RESULT_STATUS = "Command/Result/Status"  # a method's Status output (OPC 40010's methods have one), else null


@dataclass
class Command:
    metric: str  # "Command/Reset"
    methods: list[BoundMethod]
    datatype: DataType
    structure: ua.Argument | None = None  # PackML Start's Parameter (PackMLDescriptorDataType[])

    @staticmethod
    def status_output(bound: BoundMethod, outputs: Sequence[ua.Variant]) -> int | None:
        """The ``Status`` output argument of a call (Robotics' GetReady, LoadByName, ...), if it has one."""
        names = [a.Name for a in bound.outputs]
        if "Status" not in names or names.index("Status") >= len(outputs):
            return None
        value = outputs[names.index("Status")].Value
        return int(value) if isinstance(value, int) else None

    def pick(self) -> BoundMethod:
        """The first method whose Executable (as last published) is not false, else the first."""
        return next((b for b in self.methods if b.last_executable is not False), self.methods[0])

    def inputs(self, value: Any, datatype: DataType, parameters: dict[int, float]) -> list[ua.Variant] | None:
        """The call's input arguments, or None when a Boolean trigger was not set to true."""
        bound = self.methods[0]
        if self.structure is not None:
            if value is not True:
                return None
            cls = ua.extension_objects_by_datatype[self.structure.DataType]
            items = [cls(ID=i, Name="", Value=float(v)) for i, v in sorted(parameters.items())]
            return [ua.Variant(items, ua.VariantType.ExtensionObject, is_array=True)]
        if not bound.inputs:
            return [] if value is True else None
        return [ua.Variant(value, VARIANTS.get(datatype, ua.VariantType.String))]


def resolve(
    declared: Sequence[DeclaredCommand],
    part_node: ua.NodeId,
    methods: dict[ua.NodeId, BoundMethod],
    builtin_of: Builtin,
    prefix: str = PREFIX,
) -> list[Command]:
    """The ``declared`` commands of a part the server has bound (cell NodeIds are the paths)."""
    commands = []
    for name, targets in declared:
        bound = []
        for obj, method in targets:
            path = ".".join(p for p in (str(part_node.Identifier), obj.replace("/", ".")) if p)
            found = methods.get(ua.NodeId(f"{path}.{method}", part_node.NamespaceIndex))
            if found is not None:
                bound.append(found)
        if bound:
            commands.append(_command(prefix + name, bound, builtin_of))
    return commands


def _command(metric: str, bound: list[BoundMethod], builtin_of: Builtin) -> Command:
    inputs: Sequence[ua.Argument] = bound[0].inputs
    if not inputs:
        return Command(metric, bound, DataType.Boolean)
    arg = inputs[0]
    vtype = builtin_of(arg.DataType)
    if len(inputs) == 1 and arg.ValueRank >= 1 and vtype is ua.VariantType.ExtensionObject:
        return Command(metric, bound, DataType.Boolean, structure=arg)
    return Command(metric, bound, datatype_of(vtype, arg.ValueRank >= 0))


def parameters_of(metric: str, values: dict[str, Any]) -> dict[int, float]:
    """``Command/Start/Parameter/<ID>`` metrics of one DCMD: ID -> value."""
    found: dict[int, float] = {}
    head = f"{metric}/Parameter/"
    for name, value in values.items():
        if name.startswith(head) and name[len(head) :].lstrip("-").isdigit() and isinstance(value, int | float):
            found[int(name[len(head) :])] = float(value)
    return found
