"""Binds each PackML unit of the cell (role ``packml_unit``) to its PackMLBaseObjectType instance.

The pure ``PackMLUnit`` owns every rule; this module only translates: the three machines go through
the shared state-machine binding, every method through the dispatcher, Status/Admin values from the
model's listener to the address space (typed by each variable's DataType), and asyncua structure
values to and from the model's dataclasses. Server-defined additions, in the cell namespace:
``<unit>/Status/StartParameters`` (the last accepted Start's parameters) and
``<unit>/InjectFault(Id, Message)`` (engineer and admin: simulate an equipment fault).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import inspect
import logging
from collections.abc import Awaitable, Callable, Sequence
from datetime import datetime
from datetime import time as dt_time
from typing import TYPE_CHECKING, Any

from asyncua import ua

from uacell.binding.cell import BuiltPart
from uacell.binding.conditions import ConditionNodes, ConditionPlace
from uacell.core.background import Background
from uacell.core.capabilities import has
from uacell.core.companion import Closer
from uacell.core.drivers import PACKML_UNIT, SIMULATORS
from uacell.core.equipment_factory import EquipmentSpec, choose_equipment, make_equipment
from uacell.core.errors import ConfigError
from uacell.core.registry import RegistryKey
from uacell.core.roles import Family
from uacell.packml.admin_store import AdminStore, AdminWriter
from uacell.packml.companion import PACKML, UNIT_PART
from uacell.packml.config import PackMLConfig, UnitSpec
from uacell.packml.equipment import CommandForwarder, PackMLEquipment
from uacell.packml.model import BASE, EXECUTE, MACHINE, UNIT, PackMLTables, PackMLUnit, run_units
from uacell.packml.oee import parse_shifts
from uacell.packml.shape import (
    DESCRIPTOR_TYPE,
    INJECT_FAULT,
    add_inject_fault,
    add_oee,
    add_start_parameters,
)
from uacell.packml.sim import SimulatedUnit
from uacell.packml.types import (
    EUInformation,
    PackMLAlarmDataType,
    PackMLCountDataType,
    PackMLDescriptorDataType,
    PackMLIngredientsDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
)
from uacell.ua.context import Caller

if TYPE_CHECKING:
    from uacell.host import BinderHost

log = logging.getLogger(__name__)

PACKML_URI = "http://opcfoundation.org/UA/PackML/"
# DataType ids of the PackML structures (OPC 30050 NodeSet, namespace PACKML_URI).
# (PackMLDescriptorDataType's, 16, is uacell.packml.shape's DESCRIPTOR_TYPE)
COUNT_TYPE, ALARM_TYPE, INGREDIENTS_TYPE, PRODUCT_TYPE, REMOTE_TYPE = 14, 15, 17, 18, 19
MODE_ENUM = "ProductionMaintenanceModeEnum"
TICK_PERIOD = 0.1
_A = ua.AttributeIds
_PLAIN = (bool, int, float, str)  # model values that go into a Variant as they are
# Every bound unit, keyed by its browse path ("Filler1").
UNITS: RegistryKey[UnitBinding] = RegistryKey("PackML unit")


# --- asyncua structures -> model ----------------------------------------------------------------


def _text(t: Any) -> str:
    if isinstance(t, ua.LocalizedText):
        return t.Text or ""
    return "" if t is None else str(t)


def eu_from_ua(eu: Any) -> EUInformation:
    if eu is None:
        return EUInformation()
    return EUInformation(eu.NamespaceUri or "", int(eu.UnitId), _text(eu.DisplayName), _text(eu.Description))


def descriptor_from_ua(d: Any) -> PackMLDescriptorDataType:
    return PackMLDescriptorDataType(d.ID, d.Name or "", eu_from_ua(d.Unit), d.Value)


def descriptors_from_ua(items: Sequence[Any] | None) -> list[PackMLDescriptorDataType]:
    return [descriptor_from_ua(d) for d in items or []]


def product_from_ua(p: Any) -> PackMLProductDataType:
    ingredients = tuple(
        PackMLIngredientsDataType(i.IngredientID, tuple(descriptors_from_ua(i.Parameter))) for i in p.Ingredients or []
    )
    return PackMLProductDataType(p.ProductID, tuple(descriptors_from_ua(p.ProcessVariables)), ingredients)


def remote_from_ua(r: Any) -> PackMLRemoteInterfaceDataType:
    return PackMLRemoteInterfaceDataType(
        r.Number, r.ControlCmdNumber, r.CmdValue, tuple(descriptors_from_ua(r.Parameter))
    )


# --- model -> asyncua structures ----------------------------------------------------------------


class Structures:
    """Builds the server's registered PackML structure classes from the model's dataclasses."""

    def __init__(self, packml_ns: int) -> None:
        self.ns = packml_ns

    def cls(self, identifier: int) -> type:
        # Looked up on use: the classes are (re)registered when a server loads the PackML NodeSet.
        cls: type = ua.extension_objects_by_datatype[ua.NodeId(identifier, self.ns)]
        return cls

    def convert(self, value: Any) -> Any:
        """A model value (dataclass, list, tuple range, scalar) as the value to put in a Variant."""
        if isinstance(value, _PLAIN):
            return value
        if isinstance(value, list):
            return [v if isinstance(v, _PLAIN) else self.convert(v) for v in value]
        if isinstance(value, EUInformation):
            return ua.EUInformation(
                NamespaceUri=value.namespace_uri,
                UnitId=value.unit_id,
                DisplayName=ua.LocalizedText(value.display_name),
                Description=ua.LocalizedText(value.description),
            )
        if isinstance(value, PackMLDescriptorDataType):
            return self.cls(DESCRIPTOR_TYPE)(value.id, value.name, self.convert(value.unit), value.value)
        if isinstance(value, PackMLCountDataType):
            return self.cls(COUNT_TYPE)(value.id, value.name, self.convert(value.unit), value.count, value.acc_count)
        if isinstance(value, PackMLAlarmDataType):
            return self.cls(ALARM_TYPE)(
                value.id,
                value.value,
                value.message,
                value.category,
                _utc(value.date_time),
                _utc(value.ack_date_time),
                value.trigger,
            )
        if isinstance(value, PackMLIngredientsDataType):
            return self.cls(INGREDIENTS_TYPE)(value.ingredient_id, self.convert(list(value.parameter)))
        if isinstance(value, PackMLProductDataType):
            return self.cls(PRODUCT_TYPE)(
                value.product_id, self.convert(list(value.process_variables)), self.convert(list(value.ingredients))
            )
        if isinstance(value, PackMLRemoteInterfaceDataType):
            return self.cls(REMOTE_TYPE)(
                value.number, value.control_cmd_number, value.cmd_value, self.convert(list(value.parameter))
            )
        if isinstance(value, tuple) and len(value) == 2:  # an EURange (low, high)
            return ua.Range(float(value[0]), float(value[1]))
        return value


def _utc(t: datetime | None) -> datetime:
    # A missing UtcTime is OPC UA's null DateTime (encodes as 0).
    return t if t is not None else ua.get_win_epoch()


# --- the binding ----------------------------------------------------------------------------------


# Values uacell keeps itself, readable while the PLC is away: the warnings (communication lost is one).
_UACELLS_OWN = frozenset({"Admin/Warning", "Admin/WarningExtent"})


class UnitBinding:
    """One PackML unit on its instance node."""

    def __init__(self, app: BinderHost, built: BuiltPart, unit: PackMLUnit) -> None:
        self.app = app
        self.built = built
        self.unit = unit
        self.node: ua.NodeId = built.node
        self.ns: int = app.cell.instantiator.ns
        self.structures = Structures(app.model_indexes["PackML"])
        self.variables: dict[str, tuple[ua.NodeId, ua.VariantType, int]] = {}  # key -> node, type, rank
        self._reachable = True  # what the values last said about the equipment's PLC
        self.values = app.space.value_writer(app.dispatcher.types.builtin_of)
        self.conditions: ConditionNodes | None = None  # when the equipment declares conditions

    # nodes ------------------------------------------------------------------------------------
    def child(self, path: str) -> ua.NodeId:
        return self.app.cell.child(self.node, path)

    def _variable(self, key: str) -> tuple[ua.NodeId, ua.VariantType, int] | None:
        if key not in self.variables:
            try:
                nodeid = self.child(key)
            except KeyError:
                log.warning("%s has no %s; not published", self.unit.name, key)
                return None
            datatype = self.app.space.attribute(nodeid, _A.DataType)
            rank = self.app.space.attribute(nodeid, _A.ValueRank)
            vtype = self.app.dispatcher.types.builtin_of(datatype) or ua.VariantType.Variant
            self.variables[key] = (nodeid, vtype, rank)
        return self.variables[key]

    async def add_start_parameters(self) -> None:
        """The server-defined read-only ``Status/StartParameters`` (PackMLDescriptorDataType[])."""
        # made with the cell before the snapshot (uacell.packml.shape); here where it is not
        await add_start_parameters(self.app.space, self.child("Status"), self.built.path, self.ns, self.structures.ns)

    async def add_oee(self) -> None:
        """``OEE`` under the unit (uacell's namespace): the figures of ``uacell.packml.oee``, read-only."""
        # made with the cell before the snapshot (uacell.packml.shape); here where they are not
        await add_oee(self.app.space, self.node, self.built.path, self.ns)

    async def add_conditions(self) -> None:
        """``Conditions`` under the unit (uacell's namespace): the alarm conditions its equipment
        declares (a gateway's CommunicationLost; decision 45), bound as every part's are."""
        if not self.unit.conditions.conditions:
            return
        path = f"{self.built.path}.Conditions"
        space = self.app.space
        folder = await space.add_folder(self.node, ua.NodeId(path, self.ns), ua.QualifiedName("Conditions", self.ns))
        # the unit is the conditions' source and notifier: its events reach clients subscribed to it
        await space.notify_events(self.node)
        place = ConditionPlace(folder, self.node, self.node, self.unit.name, path)
        d = self.app.dispatcher

        # Their Executable depends on the conditions, not on what the unit's methods depend on: a scope of
        # their own, refreshed after their calls and whenever a condition changes.
        scope = self.unit.conditions

        def bind(node: ua.NodeId, method: str, handler: Any, executable: Callable[[], bool]) -> None:
            d.bind(
                node,
                d.method_of(node, method),
                Family.CONDITION,
                handler,
                executable=executable,
                serialize_on=self.unit,
                scope=scope,
            )

        scope.condition_listeners.append(lambda _condition: d.touch(scope))

        self.conditions = ConditionNodes(self.app, self.unit.conditions, place, bind)
        await self.conditions.setup()

    async def add_inject_fault(self) -> None:
        """``InjectFault(Int32 Id, String Message)`` under the unit (engineer and above)."""
        # its node is made with the cell before the snapshot (uacell.packml.shape); here where it is not
        await add_inject_fault(self.app.space, self.node, self.built.path, self.ns)
        nodeid = ua.NodeId(f"{self.built.path}.{INJECT_FAULT}", self.ns)
        self.app.dispatcher.bind(self.node, nodeid, PACKML, self._inject_fault, serialize_on=self.unit)

    # publishing ---------------------------------------------------------------------------------
    def on_change(self, changed: dict[str, Any]) -> None:
        values = {k: v for k, v in changed.items() if k != "Executable"}
        reachable = self.unit.reachable
        if reachable != self._reachable:
            # Equipment that cannot reach its PLC: every Status and Admin value says so (its last
            # value is not the PLC's any more); once it answers again, each is written afresh.
            self._reachable = reachable
            for machine in self.unit.machines.values():  # their states: the last known, said so
                machine.set_stale(not reachable)
            if not reachable:
                self.app.publisher.submit(self._unreachable)
            else:
                values = {k: v for k, v in self.unit.values().items() if k != "Executable"}
        if not reachable:
            values = {k: v for k, v in values.items() if k in _UACELLS_OWN}
        if values:
            self.app.publisher.submit(functools.partial(self.write, values))
        if "Executable" in changed:
            # Acting states complete outside any call: the publisher's idle hook refreshes Executable
            # of this unit's methods (only).
            self.app.dispatcher.touch(self.unit)
            if not values:
                self.app.publisher.submit(_nothing)

    def variant(self, key: str, value: Any) -> ua.Variant | None:
        found = self._variable(key)
        if found is None:
            return None
        _, vtype, rank = found
        converted = self.structures.convert(value)
        if isinstance(converted, list):
            if rank >= 2:
                # Int32[][]: asyncua derives Dimensions from the nested lists; keep them for empty rows.
                dims = [len(converted), len(converted[0]) if converted else 0]
                flat = [x for row in converted for x in row]
                return ua.Variant(flat, vtype, Dimensions=dims, is_array=True)
            return ua.Variant(converted, vtype, is_array=True)
        return ua.Variant(converted, vtype)

    async def _unreachable(self) -> None:
        bad = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
        for key, (node, _, _) in list(self.variables.items()):
            if key.startswith(("Status/", "Admin/")) and key not in _UACELLS_OWN:
                await self.values.write_status(node, bad)

    async def write(self, values: dict[str, Any]) -> None:
        for key, value in values.items():
            v = self.variant(key, value)
            if v is not None:
                await self.values.write(self.variables[key][0], v, force=True)

    async def publish_constants(self) -> None:
        try:
            modes = self.app.cell.type_node("PackML", MODE_ENUM, root=ua.ObjectIds.Enumeration)
        except KeyError:
            log.warning("the PackML NodeSet has no %s", MODE_ENUM)
        else:
            await self.values.write(self.child("Status/UnitSupportedModes"), modes, ua.VariantType.NodeId, force=True)
        with contextlib.suppress(KeyError):
            await self.values.write(self.child("TagID"), self.unit.name, ua.VariantType.String, force=True)

    # methods ------------------------------------------------------------------------------------
    def bind_methods(self, machine_nodes: dict[str | None, ua.NodeId]) -> None:
        d = self.app.dispatcher
        unit = self.unit
        for machine_name, method in unit.methods():
            obj = machine_nodes[machine_name]
            d.bind(
                obj,
                d.method_of(obj, method),
                PACKML,
                self._handler(machine_name, method),
                executable=functools.partial(unit.executable, machine_name, method),
                serialize_on=unit,
            )

    def _handler(self, machine_name: str | None, method: str) -> Callable[..., Awaitable[list[Any]]]:
        convert: Callable[..., tuple[Any, ...]] = _INPUTS.get(method, _as_given)

        async def handler(caller: Caller, *values: Any) -> list[Any]:
            log.info("%s: %s.%s by %s", self.unit.name, machine_name or "unit", method, caller.display_user)
            args = convert(*values)
            equipment = self.unit.equipment
            send = equipment.send_command if has(equipment, CommandForwarder) else None
            if send is not None and (machine_name is not None or method == "SetUnitMode"):
                # A PLC that owns the state (a gateway driver): uacell's rules first, then the PLC must
                # accept the command before uacell's machines take it (docs/equipment.md, "Gateway").
                if method == "SetUnitMode":
                    self.unit.check_unit_mode(*args)
                else:
                    self.unit.check_command(machine_name, method)
                await send(machine_name, method, args)
            self.unit.command(machine_name, method, *args)
            await self.stored()
            return []

        return handler

    async def _inject_fault(self, caller: Caller, alarm_id: int, message: str) -> list[Any]:
        log.warning("%s: fault injected by %s", self.unit.name, caller.display_user)
        eq = self.unit.equipment
        if isinstance(eq, SimulatedUnit):
            eq.inject_fault(alarm_id, message or "injected fault")
        else:
            self.unit.fault(alarm_id, message or "injected fault", category=1)
        await self.stored()
        return []

    async def stored(self) -> None:
        """Wait until the unit's stored values (other than times) are durable: a call answers once the
        values it changed are published (they are published once stored, decision 28)."""
        if self.unit.store is not None and self.unit.storing:
            await self.unit.store.stored()

    # life ---------------------------------------------------------------------------------------
    async def close(self) -> None:
        self.unit.close()
        closed = self.unit.equipment_closed
        if inspect.isawaitable(closed):  # a driver's close() may be a coroutine
            await closed


def _shifts(text: str) -> tuple[dt_time, ...]:
    try:
        return parse_shifts([s.strip() for s in text.split(",") if s.strip()])
    except ValueError as e:
        raise ConfigError(f"[packml] oee_shifts: {e}") from None


def _as_given(*values: Any) -> tuple[Any, ...]:
    return values


async def _nothing() -> None:
    pass


def _start_inputs(parameter: Any) -> tuple[Any, ...]:
    return (descriptors_from_ua(parameter),)


def _products(products: Any) -> tuple[Any, ...]:
    return ([product_from_ua(p) for p in products or []],)


def _remotes(remotes: Any) -> tuple[Any, ...]:
    return ([remote_from_ua(r) for r in remotes or []],)


_INPUTS: dict[str, Callable[..., tuple[Any, ...]]] = {
    "Start": _start_inputs,
    "SetParameter": _start_inputs,
    "SetProduct": _products,
    "RemoteCommand": _remotes,
    "SetUnitMode": lambda mode: (int(mode),),
    "SetMachSpeed": lambda speed: (float(speed),),
    "SetInterlock": lambda interlock_id, state: (interlock_id, bool(state)),
}


SIMULATOR = SIMULATORS[PACKML_UNIT]


async def make_unit_equipment(app: BinderHost, built: BuiltPart) -> PackMLEquipment:
    """The unit's own factory and settings, else ``[packml] equipment``, else the simulator."""
    spec = built.part.spec if isinstance(built.part.spec, UnitSpec) else UnitSpec(built.part.name)
    cfg = app.config.section("packml", PackMLConfig)
    factory, settings = choose_equipment(
        spec.equipment,
        spec.settings,
        default=cfg.equipment,
        simulator=SIMULATOR,
        simulator_settings={"acting_time": spec.acting_time},
        simulator_defaults={"acting_time": cfg.acting_time},
    )
    if factory == SIMULATOR and spec.acting_times:
        settings["acting_times"] = {**spec.acting_times, **settings.get("acting_times", {})}
    equipment: PackMLEquipment = await make_equipment(factory, EquipmentSpec(built.path, settings), PackMLEquipment)
    return equipment


async def bind_unit(app: BinderHost, built: BuiltPart, writer: AdminWriter) -> UnitBinding:
    name = built.part.name
    spec = built.part.spec if isinstance(built.part.spec, UnitSpec) else UnitSpec(name)
    defaults = app.config.section("packml", PackMLConfig)
    mach_speed = spec.mach_speed if spec.mach_speed is not None else defaults.mach_speed
    low, high = spec.mach_speed_range
    if not low <= mach_speed <= high:
        raise ConfigError(f"{built.path}: [packml] mach_speed {mach_speed:g} is outside its range {low:g}..{high:g}")
    equipment = await make_unit_equipment(app, built)
    unit = PackMLUnit(
        equipment,
        name=name,
        store=AdminStore(app.data_dir / "packml" / f"{name}.json", writer),
        mach_speed=mach_speed,
        mach_speed_range=spec.mach_speed_range,
        mach_design_speed=spec.design_speed,
        initial_mode=spec.unit_mode,
        tables=PackMLTables.load(app.tables),
        oee_window_hours=app.config.packml.oee_window_hours,
        oee_shifts=_shifts(app.config.packml.oee_shifts),
    )
    b = UnitBinding(app, built, unit)
    base = b.child("BaseStateMachine")
    machine = app.cell.child(base, MACHINE)
    execute = app.cell.child(machine, EXECUTE)
    await app.space.bind_machine(base, unit.base, app.publisher, app.refs)
    await b.add_start_parameters()
    b.bind_methods({BASE: base, MACHINE: machine, EXECUTE: execute, UNIT: b.node})
    await b.add_inject_fault()
    await b.add_oee()
    await b.add_conditions()
    await b.publish_constants()
    values = unit.values()
    values.pop("Executable")
    await b.write(values)
    unit.listeners.append(b.on_change)
    app.registry(UNITS).add(built.path, b)
    return b


async def bind_packml(app: BinderHost) -> Closer | None:
    """The PackML binder: every part with role ``packml_unit``. One task ticks every unit, and one
    writer thread stores every unit's Admin data."""
    bindings: list[UnitBinding] = []
    writer = AdminWriter(asyncio.get_running_loop())
    background = Background()

    async def close() -> None:
        await background.close()
        for b in bindings:
            try:
                await b.close()
            except Exception:
                log.exception("closing PackML unit %s failed", b.unit.name)
        await writer.close()  # the last saves are durable, and published
        await app.publisher.flush()

    try:
        for built in app.cell.by_role(UNIT_PART):
            bindings.append(await bind_unit(app, built, writer))
    except BaseException:
        await close()  # the drivers already connected
        raise
    if not bindings:
        await writer.close()
        return None
    background.spawn(run_units([b.unit for b in bindings], TICK_PERIOD), name="packml-tick")
    return close


__all__ = ["UnitBinding", "bind_packml"]
