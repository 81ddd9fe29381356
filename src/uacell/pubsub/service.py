"""PubSub for a running server: the writers of every built part, fed by the address space and the
event tap, published through one MQTT link (docs/pubsub.md).

Per part whose role ``uacell.core.datasets`` declares: a writer of its values (named by the part's path,
e.g. ``Robot1.Controllers.Controller1``), a writer of its events (``<path>.Events``) when it has
notifiers, and for a motion device a writer of its axis positions (``<path>.Axes``) at
``positions_interval``. Writer ids follow the cell's order, so the same cell file gives the same ids.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell.core.datasets import STATE, DataSets, Item, resolve
from uacell.pubsub.address_space import PubSubNodes
from uacell.pubsub.config import PubSubConfig
from uacell.pubsub.encoding import JsonEncoder
from uacell.pubsub.messages import DISABLED, ERROR, OPERATIONAL, Field, Publisher, Topics, Writer, encode
from uacell.pubsub.mqtt import LinkSettings, MqttLink, Outgoing
from uacell.pubsub.schema import Schema, SchemaCollector, connection_config
from uacell.pubsub.versions import VersionStore
from uacell.ua import toolkit
from uacell.ua.event_tap import EventTap
from uacell.ua.instantiate import Instantiator

log = logging.getLogger(__name__)
_A = ua.AttributeIds

# The fields an event DataSetMessage carries (BaseEventType's, a TransitionEvent's, an
# AuditUpdateStateEvent's, a Condition's): every one in every message, JSON null where the event has none.
EVENT_FIELDS: tuple[tuple[str, ua.VariantType], ...] = (
    ("EventId", ua.VariantType.ByteString),
    ("EventType", ua.VariantType.NodeId),
    ("SourceNode", ua.VariantType.NodeId),
    ("SourceName", ua.VariantType.String),
    ("Time", ua.VariantType.DateTime),
    ("Message", ua.VariantType.LocalizedText),
    ("Severity", ua.VariantType.UInt16),
    ("Transition", ua.VariantType.LocalizedText),
    ("FromState", ua.VariantType.LocalizedText),
    ("ToState", ua.VariantType.LocalizedText),
    ("ClientUserId", ua.VariantType.String),
    ("MethodId", ua.VariantType.NodeId),
    ("ConditionName", ua.VariantType.String),
    ("ActiveState", ua.VariantType.LocalizedText),
    ("AckedState", ua.VariantType.LocalizedText),
    ("Retain", ua.VariantType.Boolean),
)


@dataclass(frozen=True)
class PartRef:
    role: str
    node: ua.NodeId
    path: str  # the part's NodeId path, e.g. "Robot1.Controllers.Controller1"


def default_publisher_id(port: int) -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname()) or "localhost"
    return f"uacell-{host}-{port}"


class PubSubService:
    def __init__(self, cfg: PubSubConfig, aspace: AddressSpace, encoder: JsonEncoder, publisher_id: str) -> None:
        self.cfg = cfg
        self.aspace = aspace
        self.encoder = encoder
        self.publisher = Publisher(publisher_id, cfg.writer_group)
        self.topics = Topics(cfg.topic_prefix, publisher_id, cfg.writer_group)
        self.writers: list[Writer] = []
        self._by_notifier: dict[ua.NodeId, Writer] = {}
        self.sources: dict[int, list[ua.NodeId]] = {}  # writer id -> the variables of its fields
        self.schemas: dict[int, Schema] = {}  # writer id -> its fields' DataTypes and their descriptions
        self.nodes: PubSubNodes | None = None  # the configuration in the address space
        self._handles: list[int] = []
        self._tap: EventTap | None = None
        self._task: asyncio.Task[None] | None = None
        self.schema = SchemaCollector(aspace, encoder)
        settings = LinkSettings.of(cfg, cfg.client_id or publisher_id, cfg.qos, cfg.buffer)
        self.link = MqttLink(settings, lambda: self._status(ERROR), self._retained)  # a new Will each connect
        self._dropped_reported = 0

    # -- what is published -----------------------------------------------------------------------

    def add_parts(self, parts: Iterable[PartRef], datasets: DataSets, extra: Sequence[str] = ()) -> None:
        added: dict[str, list[Item]] = {}
        for entry in extra:
            role, _, path = entry.partition(":")
            added.setdefault(role, []).append(Item(path, STATE))
        ticks = max(1, round(self.cfg.positions_interval / self.cfg.publishing_interval))
        for part in parts:
            dataset = datasets.of(part.role)
            items = [*(dataset.values if dataset else ()), *added.get(part.role, [])]
            plain = [i for i in items if not i.optional]
            positions = [i for i in items if i.optional] if self.cfg.axis_positions else []
            if plain:
                self._value_writer(part.path, part.node, plain, 1)
            if positions:
                self._value_writer(f"{part.path}.Axes", part.node, positions, ticks)
            notifiers = [n for p in (dataset.notifiers if dataset else ()) for _, n in self._resolve(p, part.node)]
            if notifiers:
                fields = tuple(
                    Field(name, vtype.value, _EVENT_TYPES.get(name, f"i={vtype.value}")) for name, vtype in EVENT_FIELDS
                )
                writer = self._writer(f"{part.path}.Events", fields, events=True)
                for node in notifiers:
                    self._by_notifier[node] = writer

    def _resolve(self, path: str, root: ua.NodeId) -> list[tuple[str, ua.NodeId]]:
        return list(resolve(path, lambda n: toolkit.children(self.aspace, n), root))

    def _writer(self, name: str, fields: tuple[Field, ...], *, events: bool = False, ticks: int = 1) -> Writer:
        writer = Writer(
            writer_id=len(self.writers) + 1,
            name=name,
            fields=fields,
            events=events,
            interval_ticks=ticks,
            keyframe_count=self.cfg.keyframe_count,
            keep_alive=float(self.cfg.keep_alive),
        )
        self.writers.append(writer)
        return writer

    def _value_writer(self, name: str, root: ua.NodeId, items: list[Item], ticks: int) -> None:
        nodes = [(path, node) for item in items for path, node in self._resolve(item.path, root)]
        if not nodes:
            return
        fields = tuple(self._field(path, node) for path, node in nodes)
        writer = self._writer(name, fields, ticks=ticks)
        schema = self.schema.describe([self._data_type(node) for _path, node in nodes])
        writer.schema = self.schema.header(schema)
        self.schemas[writer.writer_id] = schema
        self.sources[writer.writer_id] = [node for _path, node in nodes]
        for (path, node), f in zip(nodes, fields, strict=True):
            dv = self.aspace.read_attribute_value(node, _A.Value)
            writer.update(path, self.encoder.data_value(dv, typed=f.abstract, names=dict(f.names)))
            self._watch(writer, f, node)

    def _data_type(self, node: ua.NodeId) -> ua.NodeId | None:
        dt = self.aspace.read_attribute_value(node, _A.DataType).Value
        value = dt.Value if dt is not None else None
        return value if isinstance(value, ua.NodeId) else None

    def _field(self, path: str, node: ua.NodeId) -> Field:
        dv = self.aspace.read_attribute_value(node, _A.Value)
        data_type = self.aspace.read_attribute_value(node, _A.DataType).Value
        rank = self.aspace.read_attribute_value(node, _A.ValueRank).Value
        dt = data_type.Value if data_type is not None else None
        builtin = dv.Value.VariantType.value if dv.Value is not None and dv.Value.Value is not None else 0
        if not builtin and isinstance(dt, ua.NodeId) and dt.NamespaceIndex == 0 and isinstance(dt.Identifier, int):
            builtin = dt.Identifier if dt.Identifier <= 25 else 0
        return Field(
            name=path,
            builtin=builtin,
            data_type=self.encoder.node_id(dt) if isinstance(dt, ua.NodeId) else "i=24",
            value_rank=int(rank.Value) if rank is not None and rank.Value is not None else -1,
            abstract=not isinstance(dt, ua.NodeId) or self.schema.is_abstract(dt),
            names=self.schema.enum_names(dt) if isinstance(dt, ua.NodeId) else (),
        )

    def _watch(self, writer: Writer, f: Field, node: ua.NodeId) -> None:
        encoder, name, typed, names = self.encoder, f.name, f.abstract, dict(f.names)

        async def changed(_handle: int, dv: ua.DataValue) -> None:
            writer.update(name, encoder.data_value(dv, typed=typed, names=names))

        status, handle = self.aspace.add_datachange_callback(node, _A.Value, changed)
        if status.is_good():
            self._handles.append(handle)

    def _on_event(self, event: Any) -> None:
        writer = self._by_notifier.get(getattr(event, "emitting_node", None))
        if writer is None:
            return
        payload = {
            name: self.encoder.value(_plain(getattr(event, name)), vtype)
            for name, vtype in EVENT_FIELDS
            if hasattr(event, name)
        }
        writer.event(payload)  # the fields the event has not are null

    # -- the retained messages and the status --------------------------------------------------

    def _status(self, state: int) -> Outgoing:
        return Outgoing(self.topics.status(), encode(self.publisher.status_message(state)), retain=True)

    def _connection(self, now: datetime) -> Outgoing:
        config = connection_config(self.publisher, self.cfg, self.writers)
        return Outgoing(self.topics.connection(), encode(self.publisher.connection_message(config, now)), retain=True)

    def _retained(self) -> list[Outgoing]:
        now = datetime.now(UTC)
        metadata = [
            Outgoing(self.topics.metadata(w.name), encode(self.publisher.metadata_message(w, now)), retain=True)
            for w in self.writers
        ]
        return [self._status(OPERATIONAL), self._connection(now), *metadata]

    def retained_topics(self) -> list[str]:
        """The topics whose retained messages a clean stop clears (the status stays: Disabled)."""
        return [self.topics.connection(), *(self.topics.metadata(w.name) for w in self.writers)]

    # -- running ---------------------------------------------------------------------------------

    def start(self, tap: EventTap) -> None:
        self._tap = tap
        tap.listeners.append(self._on_event)
        self.link.start()
        self._task = asyncio.get_running_loop().create_task(self._publish(), name="uacell-pubsub")

    def tick(self, number: int, now: float, timestamp: datetime) -> None:
        """One publishing interval: each due writer's messages into the link's buffer."""
        for w in self.writers:
            if w.events or number % w.interval_ticks == 0:
                for message in w.due(now, timestamp):
                    payload = encode(self.publisher.network_message(message))
                    self.link.send(Outgoing(self.topics.data(w.name), payload))

    async def _publish(self) -> None:
        interval = self.cfg.publishing_interval
        number = 0
        next_at = time.monotonic()
        report_at = next_at + max(10.0, interval)
        while True:
            next_at += interval
            await asyncio.sleep(max(0.0, next_at - time.monotonic()))
            now = time.monotonic()
            if now - next_at > interval:  # fell behind (a stalled loop): skip, do not burst
                next_at = now
            try:
                self.tick(number, now, datetime.now(UTC))
                if self.nodes is not None:
                    await self.nodes.show(self.link.connected.is_set())
            except Exception:
                log.exception("pubsub: a publishing interval failed")
            number += 1
            if now >= report_at:
                report_at = now + max(10.0, interval)
                self._report_drops()

    def _report_drops(self) -> None:
        dropped = self.link.dropped - self._dropped_reported
        if dropped:
            self._dropped_reported = self.link.dropped
            log.warning(
                "pubsub: dropped %d message(s) the broker could not take in time (buffer of %d full; %d in all)",
                dropped,
                self.cfg.buffer,
                self.link.dropped,
            )

    async def stop(self) -> None:
        if self._tap is not None and self._on_event in self._tap.listeners:
            self._tap.listeners.remove(self._on_event)
        for handle in self._handles:
            self.aspace.delete_datachange_callback(handle)
        self._handles.clear()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self.tick(-1, time.monotonic(), datetime.now(UTC))  # what changed last goes out too
        await self.link.close(self._status(DISABLED), clear=self.retained_topics())
        self._report_drops()


# DataTypes of event fields that are not built-in types themselves (OPC 10000-5 BaseEventType)
_EVENT_TYPES = {"Time": "i=294"}  # UtcTime


def _plain(value: Any) -> Any:
    return value.Value if isinstance(value, ua.Variant) else value


async def install_pubsub(
    cfg: PubSubConfig,
    aspace: AddressSpace,
    instantiator: Instantiator,
    namespaces: Callable[[], Sequence[str]],
    parts: Iterable[PartRef],
    port: int,
    data_dir: Path | None = None,
    *,
    datasets: DataSets,
) -> PubSubService | None:
    """The PubSub service for ``parts``, not yet started, its configuration shown below
    Server/PublishSubscribe; None when ``[pubsub]`` is off. ``data_dir`` keeps the DataSets' versions."""
    if not cfg.enabled:
        return None
    service = PubSubService(cfg, aspace, JsonEncoder(namespaces), cfg.publisher_id or default_publisher_id(port))
    service.add_parts(parts, datasets, cfg.extra_values)
    versions = VersionStore(data_dir)
    now = datetime.now(UTC)
    for w in service.writers:
        w.version = versions.version(w.name, w.shape(), now)
    versions.save()
    service.nodes = PubSubNodes(aspace, instantiator)
    await service.nodes.build(
        service.publisher.publisher_id,
        service.link.settings.url,
        cfg.writer_group,
        cfg.publishing_interval,
        float(cfg.keep_alive),
        service.writers,
        service.sources,
        service.schemas,
    )
    log.info(
        "pubsub: %d DataSetWriters publish to %s under %s",
        len(service.writers),
        service.link.settings.url,
        service.topics.status().rsplit("/status/", 1)[0],
    )
    return service
