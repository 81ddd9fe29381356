"""Sparkplug B for a running server: the edge node's devices fed by the address space, their commands
run through the method dispatcher, published through one MQTT link (docs/sparkplug.md).

A change of a published variable updates its device's metric and, on the event loop's next turn,
goes out as DDATA (the changes of one turn in one message per device). While the broker is away, or
the primary host is offline, nothing is published; the next birth carries every current value.
A device whose values say its equipment cannot be reached (Bad_NoCommunication, as the gateway
writes them) gets a DDEATH, and a DBIRTH once they are good again.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell import __version__
from uacell.binding.dispatch import MethodDispatcher
from uacell.core.background import Background
from uacell.core.datasets import DataSets, resolve
from uacell.pubsub.mqtt import LinkSettings
from uacell.sparkplug.commands import (
    RESULT_CODE,
    RESULT_COMMAND,
    RESULT_STATUS,
    RESULT_SYMBOL,
    Command,
    parameters_of,
)
from uacell.sparkplug.commands import resolve as resolve_commands
from uacell.sparkplug.config import SparkplugConfig
from uacell.sparkplug.devices import DevicePlan, PartRef, plan_devices
from uacell.sparkplug.link import SparkplugLink
from uacell.sparkplug.node import (
    ENG_HIGH,
    ENG_LOW,
    ENG_UNIT,
    REBIRTH,
    Device,
    EdgeNode,
    Message,
    Sample,
    parse_state,
    state_topic,
)
from uacell.sparkplug.payload import DataType, decode, get_value
from uacell.sparkplug.values import datatype_of, millis, unreachable, value_of
from uacell.ua import toolkit
from uacell.ua.context import Caller

log = logging.getLogger(__name__)
_A = ua.AttributeIds
BDSEQ_FILE = "sparkplug-bdseq"


def now_ms() -> int:
    return int(time.time() * 1000)


class SparkplugService:
    def __init__(
        self,
        cfg: SparkplugConfig,
        aspace: AddressSpace,
        dispatcher: MethodDispatcher,
        edge_node_id: str,
        data_dir: Path,
    ) -> None:
        self.cfg = cfg
        self.aspace = aspace
        self.dispatcher = dispatcher
        self._bdseq_file = data_dir / BDSEQ_FILE
        self.node = EdgeNode(cfg.group_id, edge_node_id, self._last_bdseq())
        self.node.node_metrics = [("Application", DataType.String, f"uacell {__version__}")]
        self.commands: dict[str, dict[str, Command]] = {}  # device id -> metric name -> command
        self._aliases: dict[str, dict[int, str]] = {}  # device id -> alias -> metric name
        self._bad: dict[str, set[int]] = {}  # device id -> aliases whose value says "unreachable"
        self._next_alias = self.node.first_device_alias
        self._handles: list[int] = []
        self._flush_pending = False
        self._first_session = True
        self.live = False  # born in the current session (and the primary host online)
        self.host_online: bool | None = None  # None: no primary host configured
        self._host_stamp = 0
        self.caller = Caller("sparkplug", f"Sparkplug {cfg.group_id}/{edge_node_id}", "sparkplug",
                             cfg.command_role or "observer", cfg.broker)  # fmt: skip
        self._background = Background()
        subscriptions = [self.node.topic("NCMD"), self.node.topic("DCMD") + "/+"]
        if cfg.primary_host_id:
            self.host_online = False
            subscriptions.insert(0, state_topic(cfg.primary_host_id))
        client_id = cfg.client_id or f"{edge_node_id}-sparkplug"  # not [pubsub]'s (the same host-port)
        settings = LinkSettings.of(cfg, client_id, qos=0, buffer=0)
        self.link = SparkplugLink(settings, self._will, subscriptions, self._connected, self._on_message)

    # -- bdSeq: one more per connection, kept across restarts ------------------------------------

    def _last_bdseq(self) -> int:
        try:
            return (int(self._bdseq_file.read_text().strip()) + 1) % 256
        except (OSError, ValueError):
            return 0

    def _will(self) -> Message:
        if not self._first_session:
            self.node.next_session()
        self._first_session = False
        try:
            self._bdseq_file.write_text(f"{self.node.bdseq}\n")
        except OSError as exc:
            log.warning("sparkplug: cannot keep bdSeq in %s: %s", self._bdseq_file, exc)
        return self.node.ndeath(now_ms())

    # -- the devices -----------------------------------------------------------------------------

    def add_devices(self, plans: Sequence[DevicePlan]) -> None:
        for plan in plans:
            device = Device(plan.device_id)
            self.node.devices[plan.device_id] = device
            self._aliases[plan.device_id] = {}
            self._bad[plan.device_id] = set()
            commands: dict[str, Command] = {}
            for source in plan.sources:
                for item in source.items:
                    for path, node in resolve(item.path, lambda n: toolkit.children(self.aspace, n), source.part.node):
                        self._metric(device, source.prefix + path, node)
                found = resolve_commands(
                    source.commands, source.part.node, self.dispatcher.methods, self.dispatcher.types.builtin_of
                )
                for command in found:  # of two with one name, the first
                    commands.setdefault(command.metric, command)
            self.commands[plan.device_id] = commands
            stamp = now_ms()
            for command in commands.values():
                initial = False if command.datatype is DataType.Boolean else None
                self._add(device, command.metric, command.datatype, Sample(initial, stamp), transient=True)
            self._add(device, RESULT_COMMAND, DataType.String, Sample("", stamp))
            self._add(device, RESULT_CODE, DataType.UInt32, Sample(0, stamp))
            self._add(device, RESULT_SYMBOL, DataType.String, Sample("Good", stamp))
            self._add(device, RESULT_STATUS, DataType.Int32, Sample(None, stamp))
            device.reachable = not self._bad[plan.device_id]

    def _add(self, device: Device, name: str, datatype: DataType, sample: Sample, properties: Any = (),
             transient: bool = False) -> int:  # fmt: skip
        alias = self._next_alias
        self._next_alias += 1
        device.add(name, datatype, sample, properties, alias=alias, transient=transient)
        self._aliases[device.device_id][alias] = name
        return alias

    def _metric(self, device: Device, name: str, node: ua.NodeId) -> None:
        dv = self.aspace.read_attribute_value(node, _A.Value)
        data_type = self.aspace.read_attribute_value(node, _A.DataType).Value
        rank = self.aspace.read_attribute_value(node, _A.ValueRank).Value
        vtype = dv.Value.VariantType if dv.Value is not None and dv.Value.Value is not None else None
        dt = data_type.Value if data_type is not None else None
        if vtype is None and isinstance(dt, ua.NodeId):
            vtype = self.dispatcher.types.builtin_of(dt)
        array = rank is not None and rank.Value is not None and int(rank.Value) >= 0
        datatype = datatype_of(vtype, array)
        alias = self._add(device, name, datatype, Sample(value_of(dv, datatype), millis(dv.SourceTimestamp)),
                          self._properties(node))  # fmt: skip
        if unreachable(dv):
            self._bad[device.device_id].add(alias)

        async def changed(_handle: int, value: ua.DataValue) -> None:
            self.update(device, alias, datatype, value)

        status, handle = self.aspace.add_datachange_callback(node, _A.Value, changed)
        if status.is_good():
            self._handles.append(handle)

    def _properties(self, node: ua.NodeId) -> list[tuple[str, DataType, Any]]:
        """engUnit from EngineeringUnits, engLow and engHigh from EURange (an AnalogItem's)."""
        found: list[tuple[str, DataType, Any]] = []
        eu_node = toolkit.find_child(self.aspace, node, "EngineeringUnits")
        eu = self.aspace.read_attribute_value(eu_node, _A.Value).Value.Value if eu_node is not None else None
        if eu is not None and getattr(eu, "DisplayName", None) is not None and eu.DisplayName.Text:
            found.append((ENG_UNIT, DataType.String, eu.DisplayName.Text))
        range_node = toolkit.find_child(self.aspace, node, "EURange")
        rng = self.aspace.read_attribute_value(range_node, _A.Value).Value.Value if range_node is not None else None
        if rng is not None and hasattr(rng, "Low"):
            found += [(ENG_LOW, DataType.Double, float(rng.Low)), (ENG_HIGH, DataType.Double, float(rng.High))]
        return found

    def update(self, device: Device, alias: int, datatype: DataType, dv: ua.DataValue) -> None:
        """A variable's new value: the metric's sample, and whether its equipment answers."""
        device.update(alias, Sample(value_of(dv, datatype), millis(dv.SourceTimestamp)))
        bad = self._bad[device.device_id]
        if unreachable(dv):
            bad.add(alias)
        else:
            bad.discard(alias)
        device.reachable = not bad
        self._schedule()

    def _schedule(self) -> None:
        if not self._flush_pending:
            self._flush_pending = True
            asyncio.get_running_loop().call_soon(self.flush)

    def flush(self) -> None:
        """What changed since the last turn: DDATA, or DDEATH/DBIRTH where reachability changed."""
        self._flush_pending = False
        if not self.live:
            return
        now = now_ms()
        for device in self.node.devices.values():
            try:
                message = self._next_message(device, now)
            except Exception:  # one device's trouble is logged, never the others' silence
                log.exception("sparkplug: the message of %s failed", device.device_id)
                device.changed.clear()
                continue
            if message is not None:
                self.link.send(message)

    def _next_message(self, device: Device, now: int) -> Message | None:
        if device.born and not device.reachable:
            return self.node.ddeath(device, now)
        if not device.born and device.reachable:
            return self.node.dbirth(device, now)
        return self.node.ddata(device, now) if device.born else None

    # -- the session -------------------------------------------------------------------------------

    def birth(self) -> None:
        """NBIRTH (seq 0), then the DBIRTH of each device whose equipment answers."""
        now = now_ms()
        self.link.send(self.node.nbirth(now))
        for device in self.node.devices.values():
            if device.reachable:
                self.link.send(self.node.dbirth(device, now))
        self.live = True

    def _connected(self) -> None:
        self.live = False
        if self.host_online is None:
            self.birth()
        elif self.host_online:  # (a STATE of this session will say so first: it is retained)
            self.host_online = False

    async def _on_message(self, topic: str, payload: bytes) -> None:
        if self.cfg.primary_host_id and topic == state_topic(self.cfg.primary_host_id):
            self._on_state(payload)
            return
        try:
            message = decode(payload)
        except Exception:
            log.warning("sparkplug: %s: not a Sparkplug B payload; ignored", topic)
            return
        if topic == self.node.topic("NCMD"):
            rebirth = self.node.node_alias(REBIRTH)
            for metric in message.metrics:
                named = metric.name == REBIRTH if metric.HasField("name") else metric.alias == rebirth
                if named and get_value(metric, DataType.Boolean) is True and self.live:
                    log.info("sparkplug: rebirth requested")
                    self.birth()
            return
        device_id = topic.rsplit("/", 1)[-1]
        if topic == f"{self.node.topic('DCMD')}/{device_id}" and device_id in self.node.devices:
            self._on_dcmd(self.node.devices[device_id], message)

    def _on_state(self, payload: bytes) -> None:
        state = parse_state(payload)
        if state is None:
            log.warning('sparkplug: the primary host\'s STATE is not {"online": …, "timestamp": …}; ignored')
            return
        online, stamp = state
        if stamp < self._host_stamp:  # older than the STATE followed: the timestamp is for this (3.0, STATE)
            log.info(
                "sparkplug: a STATE of the primary host older than the one followed (%d < %d); ignored",
                stamp,
                self._host_stamp,
            )
            return
        self._host_stamp = stamp
        self.host_online = online
        if online and not self.live and self.link.connected.is_set():
            log.info("sparkplug: the primary host %s is online", self.cfg.primary_host_id)
            self.birth()
        elif not online and self.live:
            log.info("sparkplug: the primary host %s is offline: NDEATH, then a new session", self.cfg.primary_host_id)
            self.live = False
            self.link.send(self.node.ndeath(now_ms()))
            self.link.leave()

    # -- commands ----------------------------------------------------------------------------------

    def _on_dcmd(self, device: Device, message: Any) -> None:
        names = self._aliases[device.device_id]
        types = {m.name: m.datatype for m in device.metrics}
        values: dict[str, tuple[Any, DataType]] = {}
        for metric in message.metrics:
            name = metric.name if metric.HasField("name") else names.get(metric.alias, f"alias {metric.alias}")
            declared = types.get(name)
            datatype = DataType(metric.datatype) if metric.HasField("datatype") else declared or DataType.Unknown
            values[name] = (get_value(metric, datatype), datatype)
        commands = self.commands[device.device_id]
        plain = {name: value for name, (value, _) in values.items()}
        for name, (value, datatype) in values.items():
            command = commands.get(name)
            if command is not None:
                parameters = parameters_of(name, plain)
                self._background.spawn(self._run(device, command, value, datatype, parameters), name=f"dcmd {name}")
            elif not any(name.startswith(f"{c}/Parameter/") for c in commands):
                code = ua.StatusCodes.BadNotWritable if name in types else ua.StatusCodes.BadNodeIdUnknown
                self._result(device, name, code)

    async def _run(
        self, device: Device, command: Command, value: Any, datatype: DataType, params: dict[int, float]
    ) -> None:
        try:
            inputs = command.inputs(value, datatype, params)
        except (TypeError, ValueError):
            self._result(device, command.metric, ua.StatusCodes.BadTypeMismatch)
            return
        if inputs is None:
            return  # a trigger set to false: nothing asked
        bound = command.pick()
        request = ua.CallMethodRequest(ObjectId=bound.object_id, MethodId=bound.method_id, InputArguments=inputs)
        result = await self.dispatcher.dispatch(request, self.caller)
        status = Command.status_output(bound, result.OutputArguments or [])
        self._result(device, command.metric, result.StatusCode.value, status)

    def _result(self, device: Device, command: str, code: int, status: int | None = None) -> None:
        """The answer to a command, as the ``Command/Result/*`` metrics."""
        now = now_ms()
        by_name = {m.name: m.alias for m in device.metrics}
        symbol = ua.StatusCode(code).name
        answer = ((RESULT_COMMAND, command), (RESULT_CODE, code), (RESULT_SYMBOL, symbol), (RESULT_STATUS, status))
        for name, value in answer:
            device.update(by_name[name], Sample(value, now))
        self._schedule()

    # -- running -----------------------------------------------------------------------------------

    def start(self) -> None:
        self.link.start()

    async def stop(self) -> None:
        for handle in self._handles:
            self.aspace.delete_datachange_callback(handle)
        self._handles.clear()
        await self._background.close()
        if self.live:  # a clean goodbye: the broker will not send the Will, so the NDEATH is said
            self.flush()
            self.link.send(self.node.ndeath(now_ms()))
        self.live = False
        await self.link.close()


def install_sparkplug(
    cfg: SparkplugConfig,
    aspace: AddressSpace,
    dispatcher: MethodDispatcher,
    parts: Sequence[PartRef],
    edge_node_id: str,
    data_dir: Path,
    datasets: DataSets,
) -> SparkplugService | None:
    """The edge node for ``parts``, not yet started; None when ``[sparkplug]`` is off."""
    if not cfg.enabled:
        return None
    service = SparkplugService(cfg, aspace, dispatcher, cfg.edge_node_id or edge_node_id, data_dir)
    service.add_devices(plan_devices(datasets, parts, cfg.extra_values, cfg.axis_positions, cfg.parts))
    log.info(
        "sparkplug: edge node %s/%s with %d device(s) on %s",
        cfg.group_id,
        service.node.edge,
        len(service.node.devices),
        service.link.settings.url,
    )
    return service
