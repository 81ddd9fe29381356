"""OPC 30050 PackML data types as plain dataclasses, with the validation uacell applies to them.

The binding converts asyncua ExtensionObjects to and from these; behaviour only ever sees these.
Validation failures raise ``CallError("BadInvalidArgument", argument=...)`` whose message names the
element and its problem (decisions 25 and 27).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from enum import IntEnum
from typing import Any

from uacell.core.errors import CallError

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1
FLOAT32_MAX = 3.4028234663852886e38


class ProductionMaintenanceModeEnum(IntEnum):
    """The default PackML unit modes (OPC 30050 §6.5.2)."""

    INVALID = 0
    PRODUCE = 1
    MAINTENANCE = 2
    MANUAL = 3


@dataclass(frozen=True)
class EUInformation:
    """The fields of OPC UA EUInformation (DisplayName/Description as plain text)."""

    namespace_uri: str = ""
    unit_id: int = -1
    display_name: str = ""
    description: str = ""


@dataclass(frozen=True)
class PackMLDescriptorDataType:
    """One PackML parameter: ID, Name, Unit, Value (Float)."""

    id: int
    name: str = ""
    unit: EUInformation = field(default_factory=EUInformation)
    value: float = 0.0


@dataclass(frozen=True)
class PackMLIngredientsDataType:
    ingredient_id: int
    parameter: tuple[PackMLDescriptorDataType, ...] = ()


@dataclass(frozen=True)
class PackMLProductDataType:
    product_id: int
    process_variables: tuple[PackMLDescriptorDataType, ...] = ()
    ingredients: tuple[PackMLIngredientsDataType, ...] = ()


@dataclass(frozen=True)
class PackMLRemoteInterfaceDataType:
    number: int
    control_cmd_number: int
    cmd_value: int
    parameter: tuple[PackMLDescriptorDataType, ...] = ()


@dataclass(frozen=True)
class PackMLCountDataType:
    id: int
    name: str = ""
    unit: EUInformation = field(default_factory=EUInformation)
    count: int = 0  # since the last counter reset
    acc_count: int = 0  # never reset


@dataclass(frozen=True)
class PackMLAlarmDataType:
    id: int
    value: int = 0
    message: str = ""
    category: int = 0
    date_time: datetime | None = None
    ack_date_time: datetime | None = None
    trigger: bool = False


# --- validation -------------------------------------------------------------------------------


def _bad(argument: int, message: str) -> CallError:
    return CallError("BadInvalidArgument", message, argument=argument)


def _check_int32(value: object, what: str, argument: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not INT32_MIN <= value <= INT32_MAX:
        raise _bad(argument, f"{what} must be an Int32, got {value!r}")


def check_float(value: object, what: str, argument: int = 0) -> float:
    """``value`` as a finite Float (single precision range), else BadInvalidArgument."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _bad(argument, f"{what} must be a number, got {value!r}")
    f = float(value)
    if not math.isfinite(f) or abs(f) > FLOAT32_MAX:
        raise _bad(argument, f"{what} must be a finite Float, got {value!r}")
    return f


def validate_descriptors(
    items: Sequence[object], *, argument: int = 0, where: str = "Parameter"
) -> tuple[PackMLDescriptorDataType, ...]:
    """Check a PackMLDescriptorDataType[]: every element of the type, unique IDs, finite values."""
    seen: dict[int, int] = {}
    for i, item in enumerate(items):
        label = f"{where}[{i}]"
        if not isinstance(item, PackMLDescriptorDataType):
            raise _bad(argument, f"{label} is not a PackMLDescriptorDataType")
        _check_int32(item.id, f"{label}.ID", argument)
        if item.id in seen:
            raise _bad(argument, f"{label}.ID {item.id} is not unique (also {where}[{seen[item.id]}])")
        seen[item.id] = i
        check_float(item.value, f"{label} (ID {item.id}) Value", argument)
    return tuple(items)  # type: ignore[arg-type]


def validate_products(
    items: Sequence[object], *, argument: int = 0, where: str = "Product"
) -> tuple[PackMLProductDataType, ...]:
    """Check a PackMLProductDataType[]: unique ProductIDs, valid process variables and ingredients."""
    seen: set[int] = set()
    for i, item in enumerate(items):
        label = f"{where}[{i}]"
        if not isinstance(item, PackMLProductDataType):
            raise _bad(argument, f"{label} is not a PackMLProductDataType")
        _check_int32(item.product_id, f"{label}.ProductID", argument)
        if item.product_id in seen:
            raise _bad(argument, f"{label}.ProductID {item.product_id} is not unique")
        seen.add(item.product_id)
        validate_descriptors(item.process_variables, argument=argument, where=f"{label}.ProcessVariables")
        ingredient_ids: set[int] = set()
        for j, ing in enumerate(item.ingredients):
            ilabel = f"{label}.Ingredients[{j}]"
            if not isinstance(ing, PackMLIngredientsDataType):
                raise _bad(argument, f"{ilabel} is not a PackMLIngredientsDataType")
            _check_int32(ing.ingredient_id, f"{ilabel}.IngredientID", argument)
            if ing.ingredient_id in ingredient_ids:
                raise _bad(argument, f"{ilabel}.IngredientID {ing.ingredient_id} is not unique")
            ingredient_ids.add(ing.ingredient_id)
            validate_descriptors(ing.parameter, argument=argument, where=f"{ilabel}.Parameter")
    return tuple(items)  # type: ignore[arg-type]


def validate_remote_interfaces(
    items: Sequence[object], *, argument: int = 0, where: str = "RemoteInterface"
) -> tuple[PackMLRemoteInterfaceDataType, ...]:
    """Check a PackMLRemoteInterfaceDataType[]: Int32 fields and valid parameters."""
    for i, item in enumerate(items):
        label = f"{where}[{i}]"
        if not isinstance(item, PackMLRemoteInterfaceDataType):
            raise _bad(argument, f"{label} is not a PackMLRemoteInterfaceDataType")
        for name, value in (
            ("Number", item.number),
            ("ControlCmdNumber", item.control_cmd_number),
            ("CmdValue", item.cmd_value),
        ):
            _check_int32(value, f"{label}.{name}", argument)
        validate_descriptors(item.parameter, argument=argument, where=f"{label}.Parameter")
    return tuple(items)  # type: ignore[arg-type]


# --- JSON form (admin store) ------------------------------------------------------------------


def _eu_to_json(eu: EUInformation) -> dict[str, Any]:
    return {
        "namespace_uri": eu.namespace_uri,
        "unit_id": eu.unit_id,
        "display_name": eu.display_name,
        "description": eu.description,
    }


def _eu_from_json(d: dict[str, Any]) -> EUInformation:
    return EUInformation(
        str(d.get("namespace_uri", "")),
        int(d.get("unit_id", -1)),
        str(d.get("display_name", "")),
        str(d.get("description", "")),
    )


def count_to_json(c: PackMLCountDataType) -> dict[str, Any]:
    return {
        "id": c.id,
        "name": c.name,
        "unit": _eu_to_json(c.unit),
        "count": c.count,
        "acc_count": c.acc_count,
    }


def count_from_json(d: dict[str, Any]) -> PackMLCountDataType:
    return PackMLCountDataType(
        int(d["id"]),
        str(d.get("name", "")),
        _eu_from_json(d.get("unit", {})),
        int(d.get("count", 0)),
        int(d.get("acc_count", 0)),
    )


def _time_to_json(t: datetime | None) -> str | None:
    return t.isoformat() if t is not None else None


def _time_from_json(s: object) -> datetime | None:
    return datetime.fromisoformat(s) if isinstance(s, str) else None


def alarm_to_json(a: PackMLAlarmDataType) -> dict[str, Any]:
    return {
        "id": a.id,
        "value": a.value,
        "message": a.message,
        "category": a.category,
        "date_time": _time_to_json(a.date_time),
        "ack_date_time": _time_to_json(a.ack_date_time),
        "trigger": a.trigger,
    }


def alarm_from_json(d: dict[str, Any]) -> PackMLAlarmDataType:
    return PackMLAlarmDataType(
        int(d["id"]),
        int(d.get("value", 0)),
        str(d.get("message", "")),
        int(d.get("category", 0)),
        _time_from_json(d.get("date_time")),
        _time_from_json(d.get("ack_date_time")),
        bool(d.get("trigger")),
    )
