"""OPC 30050 PackML behaviour, free of OPC UA: the TR88 model, its data types, equipment protocol,
simulator and durable Admin data."""

from uacell.packml.admin_store import AdminStore
from uacell.packml.equipment import EquipmentBase, InstantEquipment, PackMLEquipment, UnitPort
from uacell.packml.model import BASE, EXECUTE, MACHINE, UNIT, UNIT_METHODS, Admin, PackMLTables, PackMLUnit, Status
from uacell.packml.sim import SimulatedUnit
from uacell.packml.types import (
    EUInformation,
    PackMLAlarmDataType,
    PackMLCountDataType,
    PackMLDescriptorDataType,
    PackMLIngredientsDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
    ProductionMaintenanceModeEnum,
)

__all__ = [
    "BASE",
    "EXECUTE",
    "MACHINE",
    "UNIT",
    "UNIT_METHODS",
    "Admin",
    "AdminStore",
    "EUInformation",
    "EquipmentBase",
    "InstantEquipment",
    "PackMLAlarmDataType",
    "PackMLCountDataType",
    "PackMLDescriptorDataType",
    "PackMLEquipment",
    "PackMLIngredientsDataType",
    "PackMLProductDataType",
    "PackMLRemoteInterfaceDataType",
    "PackMLTables",
    "PackMLUnit",
    "ProductionMaintenanceModeEnum",
    "SimulatedUnit",
    "Status",
    "UnitPort",
]
