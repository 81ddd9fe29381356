"""A Sparkplug B 3.0 edge node and its devices, pure: what each message carries, in which order.

Topics (3.0, 4.1): ``spBv1.0/<group>/<type>/<edge node>[/<device>]``. The node's session is one MQTT
connection: its ``bdSeq`` (0-255, one more per connection) is in the NDEATH registered as the Will
and in the NBIRTH that follows; every message after the NBIRTH (seq 0) carries the next ``seq``,
255 wrapping to 0 (3.0, 6.4.5). A device is born (DBIRTH: every metric with name, alias, datatype,
properties and value), then reports changes by alias only (DDATA), and dies (DDEATH) when its
equipment cannot be reached; a rebirth sends the NBIRTH and every living device's DBIRTH again.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from uacell.sparkplug.payload import DataType, Payload, set_value

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"
# Properties a metric's DBIRTH carries: engineering units and range (docs/sparkplug.md, "Devices and metrics").
ENG_UNIT, ENG_LOW, ENG_HIGH = "engUnit", "engLow", "engHigh"


@dataclass(frozen=True)
class Message:
    topic: str
    payload: bytes


@dataclass(frozen=True)
class MetricDef:
    name: str
    alias: int
    datatype: DataType
    properties: tuple[tuple[str, DataType, Any], ...] = ()
    transient: bool = False


@dataclass
class Sample:
    value: Any
    timestamp: int  # ms since the epoch: the source's


@dataclass
class Device:
    """One device: its metrics in birth order, the latest sample of each, and what changed since the
    last message (the aliases, in order)."""

    device_id: str
    metrics: list[MetricDef] = field(default_factory=list)
    samples: dict[int, Sample] = field(default_factory=dict)
    changed: dict[int, None] = field(default_factory=dict)
    reachable: bool = True
    born: bool = False  # a DBIRTH went out in this session and no DDEATH since

    def add(self, name: str, datatype: DataType, sample: Sample, properties: Iterable[tuple[str, DataType, Any]] = (),
            *, alias: int, transient: bool = False) -> MetricDef:  # fmt: skip
        metric = MetricDef(name, alias, datatype, tuple(properties), transient)
        self.metrics.append(metric)
        self.samples[alias] = sample
        return metric

    def update(self, alias: int, sample: Sample) -> None:
        self.samples[alias] = sample
        self.changed[alias] = None


def topic(group: str, kind: str, edge: str, device: str | None = None) -> str:
    return "/".join([NAMESPACE, group, kind, edge, *([device] if device is not None else [])])


def state_topic(host_id: str) -> str:
    """The primary host application's STATE topic (3.0, "STATE")."""
    return f"{NAMESPACE}/STATE/{host_id}"


def parse_state(payload: bytes) -> tuple[bool, int] | None:
    """(online, timestamp) of a STATE payload (``{"online": true, "timestamp": 1668114759262}``), or
    None when it is not one."""
    try:
        body = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(body, dict) or not isinstance(body.get("online"), bool):
        return None
    stamp = body.get("timestamp")
    return body["online"], stamp if isinstance(stamp, int) and not isinstance(stamp, bool) else 0


class EdgeNode:
    """The sequence numbers and the messages of one edge node; ``devices`` in birth order."""

    def __init__(self, group: str, edge: str, bdseq: int = 0) -> None:
        self.group = group
        self.edge = edge
        self.bdseq = bdseq % 256  # of the current (or next) connection
        self.seq = 0
        self.devices: dict[str, Device] = {}
        self.node_metrics: list[tuple[str, DataType, Any]] = []  # beside bdSeq and Node Control/Rebirth

    def topic(self, kind: str, device: str | None = None) -> str:
        return topic(self.group, kind, self.edge, device)

    def next_session(self) -> int:
        """The bdSeq of a new connection (one more than the last, 255 wrapping to 0)."""
        self.bdseq = (self.bdseq + 1) % 256
        return self.bdseq

    def _payload(self, now: int, *, seq: bool = True) -> Any:
        payload = Payload(timestamp=now)
        if seq:
            payload.seq = self.seq
            self.seq = (self.seq + 1) % 256
        return payload

    def ndeath(self, now: int) -> Message:
        """The NDEATH of the current bdSeq (no seq, 3.0, 6.4.5): the Will, or said before a clean goodbye."""
        payload = Payload(timestamp=now)
        _metric(payload, BDSEQ, DataType.Int64, self.bdseq, now)
        return Message(self.topic("NDEATH"), payload.SerializeToString())

    def node_alias(self, name: str) -> int:
        """The alias of a node metric (bdSeq 1, Node Control/Rebirth 2, then ``node_metrics``')."""
        names = [BDSEQ, REBIRTH, *(n for n, _, _ in self.node_metrics)]
        return names.index(name) + 1

    @property
    def first_device_alias(self) -> int:
        """Aliases are unique across the edge node (3.0, 6.4.6): devices' start after the node's."""
        return 3 + len(self.node_metrics)

    def nbirth(self, now: int) -> Message:
        """The NBIRTH: seq starts again at 0; bdSeq, Node Control/Rebirth and the node's metrics,
        each with its name and alias (3.0, 6.4.6)."""
        self.seq = 0
        payload = self._payload(now)
        metrics = [(BDSEQ, DataType.Int64, self.bdseq), (REBIRTH, DataType.Boolean, False), *self.node_metrics]
        for alias, (name, datatype, value) in enumerate(metrics, start=1):
            _metric(payload, name, datatype, value, now, alias=alias)
        for device in self.devices.values():
            device.born = False
        return Message(self.topic("NBIRTH"), payload.SerializeToString())

    def dbirth(self, device: Device, now: int) -> Message:
        payload = self._payload(now)
        for m in device.metrics:
            s = device.samples[m.alias]
            metric = _metric(payload, m.name, m.datatype, s.value, s.timestamp, alias=m.alias)
            if m.transient:
                metric.is_transient = True
            if m.properties:
                for key, datatype, value in m.properties:
                    metric.properties.keys.append(key)
                    set_value(metric.properties.values.add(type=datatype), datatype, value)
        device.changed.clear()
        device.born = True
        return Message(self.topic("DBIRTH", device.device_id), payload.SerializeToString())

    def ddata(self, device: Device, now: int) -> Message | None:
        """The metrics that changed since the last message, by alias (no name, 3.0, 6.4.6); None when
        nothing did. Each keeps its datatype: 3.0 says a DDATA SHOULD NOT carry it, but Eclipse Tahu's
        own decoder (sparkplug-payload) reads no value without it (docs/decisions.md)."""
        if not device.changed:
            return None
        payload = self._payload(now)
        types = {m.alias: m.datatype for m in device.metrics}
        for alias in device.changed:
            s = device.samples[alias]
            metric = payload.metrics.add(alias=alias, timestamp=s.timestamp, datatype=types[alias])
            set_value(metric, types[alias], s.value)
        device.changed.clear()
        return Message(self.topic("DDATA", device.device_id), payload.SerializeToString())

    def ddeath(self, device: Device, now: int) -> Message:
        device.born = False
        device.changed.clear()
        return Message(self.topic("DDEATH", device.device_id), self._payload(now).SerializeToString())


def _metric(payload: Any, name: str, datatype: DataType, value: Any, timestamp: int, alias: int | None = None) -> Any:
    metric = payload.metrics.add(name=name, timestamp=timestamp, datatype=datatype)
    if alias is not None:
        metric.alias = alias
    set_value(metric, datatype, value)
    return metric
