"""An independent Sparkplug B 3.0 host application for the tests, written from the specification (not
from uacell's code): payloads decoded with classes protoc (grpcio-tools) generates from
``sparkplug_b.proto`` beside this file; the rules a host checks (3.0, chapters 5 and 6):

- an edge node's NBIRTH has seq 0 and a bdSeq metric; its NDEATH has the same bdSeq;
- a DBIRTH comes after its node's NBIRTH, a DDATA after its device's DBIRTH;
- every message of a node after the NBIRTH has the previous seq plus one (255 wrapping to 0);
- DDATA metrics name a metric by an alias its DBIRTH gave.

What breaks a rule goes into ``errors``; each test asserts there are none.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import json
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import aiomqtt
from helpers import wait_until

PROTO = Path(__file__).with_name("sparkplug_b.proto")

# 3.0, "Data Types": datatype -> the value field that carries it
INT8, INT16, INT32, INT64, UINT8, UINT16, UINT32, UINT64 = 1, 2, 3, 4, 5, 6, 7, 8
FLOAT, DOUBLE, BOOLEAN, STRING, DATETIME, TEXT, UUID, BYTES = 9, 10, 11, 12, 13, 14, 15, 17
_FIELD = {
    **dict.fromkeys((INT8, INT16, INT32, UINT8, UINT16, UINT32), "int_value"),
    **dict.fromkeys((INT64, UINT64, DATETIME), "long_value"),
    FLOAT: "float_value",
    DOUBLE: "double_value",
    BOOLEAN: "boolean_value",
    **dict.fromkeys((STRING, TEXT, UUID), "string_value"),
    BYTES: "bytes_value",
}
_SIGNED = {INT8: 8, INT16: 16, INT32: 32, INT64: 64}


def compile_proto(out: Path) -> ModuleType:
    """The protoc-generated module of ``sparkplug_b.proto`` (compiled into ``out``)."""
    from grpc_tools import protoc

    out.mkdir(parents=True, exist_ok=True)
    code = protoc.main(["protoc", f"-I{PROTO.parent}", f"--python_out={out}", str(PROTO)])
    assert code == 0, "protoc failed on sparkplug_b.proto"
    spec = importlib.util.spec_from_file_location("sparkplug_b_pb2", out / "sparkplug_b_pb2.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def value(metric: Any, datatype: int) -> Any:
    if metric.is_null:
        return None
    name = _FIELD[datatype]
    if metric.WhichOneof("value") != name:
        return None
    v = getattr(metric, name)
    bits = _SIGNED.get(datatype)
    if bits is not None and v >= 1 << (bits - 1):
        v -= 1 << bits
    return v


@dataclass
class DeviceView:
    online: bool = False
    aliases: dict[int, str] = field(default_factory=dict)
    datatypes: dict[str, int] = field(default_factory=dict)
    values: dict[str, Any] = field(default_factory=dict)
    stamps: dict[str, int] = field(default_factory=dict)  # the metric's timestamp (ms)
    properties: dict[str, dict[str, Any]] = field(default_factory=dict)
    births: int = 0
    deaths: int = 0


@dataclass
class NodeView:
    online: bool = False
    bdseq: int | None = None
    seq: int | None = None
    births: list[int | None] = field(default_factory=list)  # bdSeq of each NBIRTH (None: it had none)
    aliases: dict[str, int] = field(default_factory=dict)  # the NBIRTH's metric names -> aliases
    deaths: list[int | None] = field(default_factory=list)  # bdSeq of each NDEATH (None: it had none)
    devices: dict[str, DeviceView] = field(default_factory=dict)


@dataclass
class Seen:
    topic: str
    kind: str
    edge: str
    device: str | None
    payload: Any
    arrived: float  # time.time() when it arrived
    raw: bytes = b""


class Host:
    """Follows every edge node of one group; publishes STATE, NCMD and DCMD as a host does."""

    def __init__(self, pb: ModuleType, port: int, group: str, host_id: str = "") -> None:
        self.pb, self.port, self.group, self.host_id = pb, port, group, host_id
        self.nodes: dict[str, NodeView] = {}
        self.seen: list[Seen] = []
        self.errors: list[str] = []
        self.client: aiomqtt.Client | None = None

    def node(self, edge: str) -> NodeView:
        return self.nodes.setdefault(edge, NodeView())

    def device(self, edge: str, device: str) -> DeviceView:
        return self.node(edge).devices.setdefault(device, DeviceView())

    def of(self, kind: str, device: str | None = None) -> list[Seen]:
        return [s for s in self.seen if s.kind == kind and (device is None or s.device == device)]

    async def wait(self, predicate: Any, timeout: float = 30.0) -> None:
        await wait_until(predicate, timeout=timeout, step=0.005)

    # -- reading -----------------------------------------------------------------------------------

    def handle(self, topic: str, data: bytes) -> None:
        levels = topic.split("/")
        if levels[0] != "spBv1.0" or len(levels) < 4 or levels[1] == "STATE" or levels[1] != self.group:
            return
        kind, edge = levels[2], levels[3]
        device = levels[4] if len(levels) > 4 else None
        payload = self.pb.Payload()
        payload.ParseFromString(data)
        self.seen.append(Seen(topic, kind, edge, device, payload, time.time(), data))
        node = self.node(edge)
        if kind in ("NBIRTH", "DBIRTH") and any(
            not (m.HasField("name") and m.HasField("alias")) for m in payload.metrics
        ):
            self.errors.append(f"{kind} {device or edge}: a metric without both name and alias (3.0, 6.4.6)")
        if kind == "NBIRTH":
            node.aliases = {m.name: m.alias for m in payload.metrics}
            bdseq = {m.name: value(m, m.datatype) for m in payload.metrics}.get("bdSeq")
            if payload.seq != 0 or bdseq is None:
                self.errors.append(f"NBIRTH with seq {payload.seq}, bdSeq {bdseq}")
            node.online, node.bdseq, node.seq = True, bdseq, payload.seq
            node.births.append(bdseq)
            for d in node.devices.values():
                d.online = False
        elif kind == "NDEATH":
            bdseq = {m.name: value(m, m.datatype) for m in payload.metrics}.get("bdSeq")
            node.deaths.append(bdseq)
            if bdseq == node.bdseq:  # an NDEATH of an older session is not this one's (3.0: the bdSeq pairs them)
                node.online = False
                for d in node.devices.values():
                    d.online = False
        elif kind in ("DBIRTH", "DDATA", "DDEATH") and device is not None:
            self._device_message(node, kind, device, payload)

    def _device_message(self, node: NodeView, kind: str, device: str, payload: Any) -> None:
        if not node.online:
            self.errors.append(f"{kind} {device} while its node is not born")
            return
        expected = ((node.seq or 0) + 1) % 256
        if payload.seq != expected:
            self.errors.append(f"{kind} {device}: seq {payload.seq}, expected {expected}")
        node.seq = payload.seq
        d = node.devices.setdefault(device, DeviceView())
        if kind == "DBIRTH":
            d.online, d.births = True, d.births + 1
            d.aliases.clear()
            for m in payload.metrics:
                d.aliases[m.alias] = m.name
                d.datatypes[m.name] = m.datatype
                d.values[m.name] = value(m, m.datatype)
                d.stamps[m.name] = m.timestamp
                props = m.properties
                d.properties[m.name] = {k: value(v, v.type) for k, v in zip(props.keys, props.values, strict=True)}
        elif kind == "DDATA":
            if not d.online:
                self.errors.append(f"DDATA {device} before its DBIRTH")
            for m in payload.metrics:
                name = d.aliases.get(m.alias)
                if name is None or m.HasField("name"):
                    self.errors.append(f"DDATA {device}: alias {m.alias} not born (name {m.name!r})")
                    continue
                d.values[name] = value(m, d.datatypes[name])
                d.stamps[name] = m.timestamp
        else:
            d.online, d.deaths = False, d.deaths + 1

    # -- writing -----------------------------------------------------------------------------------

    async def state(self, online: bool, stamp: int | None = None) -> None:
        """The host's STATE (3.0, 7.3): retained, QoS 1."""
        assert self.client is not None and self.host_id
        body = json.dumps({"online": online, "timestamp": stamp or int(time.time() * 1000)})
        await self.client.publish(f"spBv1.0/STATE/{self.host_id}", body, qos=1, retain=True)

    async def rebirth(self, edge: str, by_alias: bool = False) -> None:
        """NCMD ``Node Control/Rebirth`` = true, by name or (as 3.0, 6.4.6 wants it) by the NBIRTH's alias."""
        payload = self.pb.Payload(timestamp=int(time.time() * 1000))
        if by_alias:
            payload.metrics.add(alias=self.node(edge).aliases["Node Control/Rebirth"], boolean_value=True)
        else:
            payload.metrics.add(name="Node Control/Rebirth", datatype=BOOLEAN, boolean_value=True)
        assert self.client is not None
        await self.client.publish(f"spBv1.0/{self.group}/NCMD/{edge}", payload.SerializeToString(), qos=0)

    async def dcmd(self, edge: str, device: str, *metrics: tuple[str, int, Any], by_alias: bool = False) -> None:
        """A DCMD writing ``metrics`` (name, datatype, value): by name, or by the alias the DBIRTH gave."""
        payload = self.pb.Payload(timestamp=int(time.time() * 1000))
        names = {n: a for a, n in self.device(edge, device).aliases.items()}
        for name, datatype, v in metrics:
            m = payload.metrics.add(datatype=datatype)
            if by_alias:
                m.alias = names[name]
            else:
                m.name = name
            if datatype in _SIGNED and v < 0:
                v += 1 << _SIGNED[datatype]
            setattr(m, _FIELD[datatype], v)
        assert self.client is not None
        await self.client.publish(f"spBv1.0/{self.group}/DCMD/{edge}/{device}", payload.SerializeToString(), qos=0)


@contextlib.asynccontextmanager
async def following(pb: ModuleType, port: int, group: str, host_id: str = "", **client: Any) -> AsyncIterator[Host]:
    """A host following ``group`` on the broker at ``port`` (subscribed before it yields); ``client``:
    aiomqtt.Client's username, password, tls_context."""
    host = Host(pb, port, group, host_id)
    ready = asyncio.Event()

    async def run() -> None:
        async with aiomqtt.Client("127.0.0.1", port, **client) as c:
            host.client = c
            await c.subscribe(f"spBv1.0/{group}/#", qos=1)
            ready.set()
            async for message in c.messages:
                payload = message.payload if isinstance(message.payload, bytes | bytearray) else b""
                host.handle(str(message.topic), bytes(payload))

    task = asyncio.ensure_future(run())
    try:
        waiter = asyncio.ensure_future(ready.wait())
        await asyncio.wait({waiter, task}, timeout=15, return_when=asyncio.FIRST_COMPLETED)
        if task.done():
            task.result()
        assert ready.is_set(), "the host did not subscribe"
        yield host
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await task
