"""Turn history on for a server: the store, the HistoryRead service, what is kept, the capabilities.

What is kept is ``uacell.core.datasets``' declaration for every built part, plus every event fired through
the Server object. Each kept variable gets Historizing, AccessLevel's HistoryRead bit and a
``HA Configuration`` (HistoricalDataConfigurationType, Stepped) by HasHistoricalConfiguration.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.server.address_space import AttributeValue, NodeData

from uacell.core.datasets import DataSets, resolve
from uacell.history.backends import Backend, SqliteBackend
from uacell.history.config import HistoryConfig
from uacell.history.processed import AGGREGATES
from uacell.history.service import HistoryService, mark_historizing
from uacell.history.store import HistoryStore, StoreSettings
from uacell.ua import door, toolkit
from uacell.ua.event_tap import EventTap

log = logging.getLogger(__name__)

_A = ua.AttributeIds
SQLITE_FILE = "history.sqlite"


def make_backend(cfg: HistoryConfig, data_dir: Path) -> Backend:
    if cfg.backend == "postgresql":
        from uacell.history.postgres import PostgresBackend

        return PostgresBackend(cfg.postgresql_dsn)
    return SqliteBackend(data_dir / SQLITE_FILE)


def settings_of(cfg: HistoryConfig) -> StoreSettings:
    return StoreSettings(flush_interval=cfg.flush_interval, max_age_days=cfg.max_age_days, max_mb=cfg.max_mb)


async def install_history(
    server: Server,
    cfg: HistoryConfig,
    data_dir: Path,
    parts: Iterable[tuple[str, ua.NodeId]],
    allows: Callable[[str], bool],
    tap: EventTap,
    datasets: DataSets,
) -> HistoryService | None:
    """Keep what ``datasets`` declare for ``parts`` (role, node) and answer HistoryRead for
    callers whose role ``allows``; None when ``[history]`` is off (then every HistoryRead and
    HistoryUpdate item answers Bad_HistoryOperationUnsupported: ``NoHistory``)."""
    if not cfg.enabled:
        door.swap(server.iserver, "InternalServer.history_manager", NoHistory())
        return None
    store = HistoryStore(make_backend(cfg, data_dir), settings_of(cfg))
    service = HistoryService(server.iserver, store, allows, cfg.max_values_per_request, cfg.max_events_per_request)
    await service.install(tap)
    parts = list(parts)
    configurations = _Configurations(server)
    for node in kept_values(server, cfg, parts, datasets):
        await service.historize_value(node)
        await configurations.add(node)  # when the snapshot did not hold it (a variable a binder added)
    children = _children(server)  # listed after the configurations were added
    for role, root in parts:
        dataset = datasets.of(role)
        for path in dataset.notifiers if dataset is not None else ():
            for _path, node in resolve(path, children, root):
                await service.historize_events(node)
    await service.historize_events(ua.NodeId(ua.ObjectIds.Server))
    await publish_capabilities(server, cfg)
    return service


class NoHistory:
    """asyncua's HistoryManager when ``[history] enabled = false``: nothing is kept, so every item of
    a HistoryRead or HistoryUpdate is Bad_HistoryOperationUnsupported (OPC 10000-4 5.10.3), never
    Good with no values (asyncua's own manager would answer from an empty memory store)."""

    async def init(self) -> None:
        return None

    async def stop(self) -> None:
        return None

    async def read_history(self, params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        return [ua.HistoryReadResult(StatusCode=_unsupported()) for _ in params.NodesToRead or ()]

    def update_history(self, params: ua.HistoryUpdateParameters) -> list[ua.HistoryUpdateResult]:
        return [ua.HistoryUpdateResult(StatusCode=_unsupported()) for _ in params.HistoryUpdateDetails or ()]


def _unsupported() -> ua.StatusCode:
    return ua.StatusCode(ua.StatusCodes.BadHistoryOperationUnsupported)


def _children(server: Server) -> Callable[[ua.NodeId], list[tuple[str, ua.NodeId]]]:
    """A node's children (``toolkit.children``), each node's listed once: the items of a part's
    DataSet share their parents (a unit's Status holds twenty of them)."""
    aspace = server.iserver.aspace
    listed: dict[ua.NodeId, list[tuple[str, ua.NodeId]]] = {}

    def children(node: ua.NodeId) -> list[tuple[str, ua.NodeId]]:
        found = listed.get(node)
        if found is None:
            found = listed[node] = toolkit.children(aspace, node)
        return found

    return children


def kept_values(
    server: Server, cfg: HistoryConfig, parts: Iterable[tuple[str, ua.NodeId]], datasets: DataSets
) -> list[ua.NodeId]:
    """The variables whose values are kept: each part's DataSet values (found in the address space
    as it is now), axis positions only with ``axis_positions``."""
    children = _children(server)
    out: list[ua.NodeId] = []
    for role, root in parts:
        dataset = datasets.of(role)
        for item in dataset.values if dataset is not None else ():
            if item.optional and not cfg.axis_positions:
                continue
            out.extend(node for _path, node in resolve(item.path, children, root))
    return out


async def add_configurations(
    server: Server, cfg: HistoryConfig, parts: Iterable[tuple[str, ua.NodeId]], datasets: DataSets
) -> None:
    """The HA Configuration of every kept variable that has none yet, and its Historizing and
    HistoryRead bits (``mark_historizing``). ``uacell.server`` calls it before the address-space
    snapshot is taken, so that restarts find them in it (the snapshot's key includes
    ``history_shape``); ``install_history`` adds those of the variables binders add later."""
    if not cfg.enabled:
        return
    configurations = _Configurations(server)
    aspace = server.iserver.aspace
    for node in kept_values(server, cfg, parts, datasets):
        await configurations.add(node)
        await mark_historizing(aspace, node)


def history_shape(cfg: HistoryConfig) -> str:
    """What of ``[history]`` shapes the address space (the HA Configuration nodes): for the snapshot key."""
    return f"history={cfg.enabled},axes={cfg.axis_positions}"


# The HA Configuration of a kept variable (OPC 10000-11 5.2.2) with the aggregate configuration
# uacell's processed reads use (uacell.history.processed: Only Good values count, 100 % Good).
_AGGREGATE_CONFIGURATION = (
    ("TreatUncertainAsBad", True, ua.VariantType.Boolean),
    ("PercentDataBad", 100, ua.VariantType.Byte),
    ("PercentDataGood", 100, ua.VariantType.Byte),
    ("UseSlopedExtrapolation", False, ua.VariantType.Boolean),
)


class _Configurations:
    """Makes the HA Configuration (OPC 10000-11 5.2.2) of kept variables: Stepped, the aggregate
    configuration.

    The first one is added through asyncua (mandatory children only, built as nodes directly: its
    generic instantiation browses the type for every one of them); the next ones are copies of it
    with their own NodeIds, made as node data (a large cell has hundreds: a quarter of its restart
    went into adding them one request each)."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self._template: tuple[ua.NodeId, list[ua.NodeId]] | None = None  # (its variable, its nodes)

    async def add(self, node: ua.NodeId) -> None:
        if not isinstance(node.Identifier, str):
            return
        ids = _configuration_ids(node)
        aspace = self.server.iserver.aspace
        if ids[0] in aspace:
            return
        if self._template is not None:
            _copy(aspace, *self._template, node, ids)
            return
        o = ua.ObjectIds
        config_id, aggregate_id = ids[0], ids[1]
        items = [
            _object(
                config_id, node, o.HasHistoricalConfiguration, "HA Configuration", o.HistoricalDataConfigurationType
            ),
            _object(aggregate_id, config_id, o.HasComponent, "AggregateConfiguration", o.AggregateConfigurationType),
            _property(config_id, "Stepped", True, ua.VariantType.Boolean),
            *(_property(aggregate_id, name, value, vtype) for name, value, vtype in _AGGREGATE_CONFIGURATION),
        ]
        results = await self.server.iserver.isession.add_nodes(items)
        bad = [r.StatusCode for r in results if not r.StatusCode.is_good()]
        if bad:
            raise RuntimeError(f"cannot add the HA Configuration of {node.to_string()}: {bad[0].name}")
        self._template = (node, ids)


def _configuration_ids(node: ua.NodeId) -> list[ua.NodeId]:
    """The NodeIds of a variable's HA Configuration: the object, its AggregateConfiguration, Stepped,
    then the aggregate configuration's properties."""
    config = f"{node.Identifier}.HAConfiguration"
    aggregate = f"{config}.AggregateConfiguration"
    names = [config, aggregate, f"{config}.Stepped", *(f"{aggregate}.{n}" for n, _v, _t in _AGGREGATE_CONFIGURATION)]
    return [ua.NodeId(name, node.NamespaceIndex) for name in names]


def _copy(
    aspace: Any, template_var: ua.NodeId, template: list[ua.NodeId], var: ua.NodeId, ids: list[ua.NodeId]
) -> None:
    """The template's nodes once more for ``var``: same attributes and references, but each NodeId of
    the template (and its variable) replaced by the new one; ``var`` refers to its configuration."""
    mapping = dict(zip(template, ids, strict=True)) | {template_var: var}
    for old, new in zip(template, ids, strict=True):
        source = aspace[old]
        data = NodeData(new)
        data.attributes = {attr: AttributeValue(value.value) for attr, value in source.attributes.items()}
        data.attributes[ua.AttributeIds.NodeId] = AttributeValue(ua.DataValue(ua.Variant(new, ua.VariantType.NodeId)))
        data.references = [
            dataclasses.replace(ref, NodeId=mapping[ref.NodeId]) if ref.NodeId in mapping else ref
            for ref in source.references
        ]
        aspace[new] = data
    forward = next(r for r in aspace[template_var].references if r.NodeId == template[0] and r.IsForward)
    aspace[var].references.append(dataclasses.replace(forward, NodeId=ids[0]))


def _object(nodeid: ua.NodeId, parent: ua.NodeId, reference: int, name: str, typedef: int) -> ua.AddNodesItem:
    attrs = ua.ObjectAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.EventNotifier = 0
    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(reference),
        RequestedNewNodeId=nodeid,
        BrowseName=ua.QualifiedName(name, 0),
        NodeClass=ua.NodeClass.Object,
        NodeAttributes=attrs,
        TypeDefinition=ua.NodeId(typedef),
    )


def _property(parent: ua.NodeId, name: str, value: object, vtype: ua.VariantType) -> ua.AddNodesItem:
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.Value = ua.Variant(value, vtype)
    attrs.DataType = ua.NodeId(vtype.value)
    attrs.ValueRank = ua.ValueRank.Scalar
    attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasProperty),
        RequestedNewNodeId=ua.NodeId(f"{parent.Identifier}.{name}", parent.NamespaceIndex),
        BrowseName=ua.QualifiedName(name, 0),
        NodeClass=ua.NodeClass.Variable,
        NodeAttributes=attrs,
        TypeDefinition=ua.NodeId(ua.ObjectIds.PropertyType),
    )


async def publish_capabilities(server: Server, cfg: HistoryConfig) -> None:
    """Server.ServerCapabilities.HistoryServerCapabilities: what HistoryRead does here."""
    ids = ua.ObjectIds
    values = {
        ids.HistoryServerCapabilities_AccessHistoryDataCapability: True,
        ids.HistoryServerCapabilities_AccessHistoryEventsCapability: True,
        ids.HistoryServerCapabilities_MaxReturnDataValues: ua.Variant(
            cfg.max_values_per_request, ua.VariantType.UInt32
        ),
        ids.HistoryServerCapabilities_MaxReturnEventValues: ua.Variant(
            cfg.max_events_per_request, ua.VariantType.UInt32
        ),
        ids.HistoryServerCapabilities_InsertDataCapability: False,
        ids.HistoryServerCapabilities_ReplaceDataCapability: False,
        ids.HistoryServerCapabilities_UpdateDataCapability: False,
        ids.HistoryServerCapabilities_DeleteRawCapability: False,
        ids.HistoryServerCapabilities_DeleteAtTimeCapability: False,
        ids.HistoryServerCapabilities_InsertAnnotationCapability: False,
        ids.HistoryServerCapabilities_InsertEventCapability: False,
        ids.HistoryServerCapabilities_ReplaceEventCapability: False,
        ids.HistoryServerCapabilities_UpdateEventCapability: False,
        ids.HistoryServerCapabilities_DeleteEventCapability: False,
        ids.HistoryServerCapabilities_ServerTimestampSupported: True,
    }
    aspace = server.iserver.aspace
    for nid, value in values.items():
        node = ua.NodeId(nid)
        if node not in aspace:
            continue
        variant = value if isinstance(value, ua.Variant) else ua.Variant(value, ua.VariantType.Boolean)
        await aspace.write_attribute_value(node, _A.Value, ua.DataValue(variant))
    folder = ua.NodeId(ids.HistoryServerCapabilities_AggregateFunctions)
    if folder in aspace:
        f = Node(server.iserver.isession, folder)
        present = {r.NodeId for r in await f.get_references(ua.ObjectIds.Organizes)}
        for agg in AGGREGATES:
            if ua.NodeId(agg) not in present:
                await f.add_reference(ua.NodeId(agg), ua.ObjectIds.Organizes, forward=True, bidirectional=False)
