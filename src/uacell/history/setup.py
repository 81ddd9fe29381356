"""Turn history on for a server: the store, the HistoryRead service, what is kept, the capabilities.

What is kept is ``uacell.datasets``' declaration for every built part, plus every event fired through
the Server object. Each kept variable gets Historizing, AccessLevel's HistoryRead bit and a
``HA Configuration`` (HistoricalDataConfigurationType, Stepped) by HasHistoricalConfiguration.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path

from asyncua import Node, Server, ua

from uacell.catalog import dataset_of
from uacell.datasets import resolve
from uacell.history.backends import Backend, SqliteBackend
from uacell.history.config import HistoryConfig
from uacell.history.processed import AGGREGATES
from uacell.history.service import HistoryService
from uacell.history.store import HistoryStore, StoreSettings
from uacell.ua import toolkit
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
) -> HistoryService | None:
    """Keep what ``uacell.datasets`` declares for ``parts`` (role, node) and answer HistoryRead for
    callers whose role ``allows``; None when ``[history]`` is off."""
    if not cfg.enabled:
        return None
    store = HistoryStore(make_backend(cfg, data_dir), settings_of(cfg))
    service = HistoryService(server.iserver, store, allows, cfg.max_values_per_request)
    await service.install(tap)
    aspace = server.iserver.aspace

    def children(node: ua.NodeId) -> list[tuple[str, ua.NodeId]]:
        return toolkit.children(aspace, node)

    parts = list(parts)
    for node in kept_values(server, cfg, parts):
        await service.historize_value(node)
        await _configuration(server, node)  # when the snapshot did not hold it (a variable a binder added)
    for role, root in parts:
        dataset = dataset_of(role)
        for path in dataset.notifiers if dataset is not None else ():
            for _path, node in resolve(path, children, root):
                await service.historize_events(node)
    await service.historize_events(ua.NodeId(ua.ObjectIds.Server))
    await publish_capabilities(server, cfg)
    return service


def kept_values(server: Server, cfg: HistoryConfig, parts: Iterable[tuple[str, ua.NodeId]]) -> list[ua.NodeId]:
    """The variables whose values are kept: each part's DataSet values (found in the address space
    as it is now), axis positions only with ``axis_positions``."""
    aspace = server.iserver.aspace

    def children(node: ua.NodeId) -> list[tuple[str, ua.NodeId]]:
        return toolkit.children(aspace, node)

    out: list[ua.NodeId] = []
    for role, root in parts:
        dataset = dataset_of(role)
        for item in dataset.values if dataset is not None else ():
            if item.optional and not cfg.axis_positions:
                continue
            out.extend(node for _path, node in resolve(item.path, children, root))
    return out


async def add_configurations(server: Server, cfg: HistoryConfig, parts: Iterable[tuple[str, ua.NodeId]]) -> None:
    """The HA Configuration of every kept variable that has none yet. ``uacell.server`` calls it
    before the address-space snapshot is taken, so that restarts find them in it (the snapshot's key
    includes ``history_shape``); ``install_history`` adds those of the variables binders add later."""
    if not cfg.enabled:
        return
    for node in kept_values(server, cfg, parts):
        await _configuration(server, node)


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


async def _configuration(server: Server, node: ua.NodeId) -> None:
    """The variable's HA Configuration (OPC 10000-11 5.2.2): Stepped, the aggregate configuration.

    Built as nodes directly (mandatory children only): asyncua's generic instantiation browses the
    type for every one of them, a quarter of a restart's time with history on."""
    if not isinstance(node.Identifier, str):
        return
    config_id = ua.NodeId(f"{node.Identifier}.HAConfiguration", node.NamespaceIndex)
    if config_id in server.iserver.aspace:
        return
    ids = ua.ObjectIds
    config_type, aggregate_type = ids.HistoricalDataConfigurationType, ids.AggregateConfigurationType
    aggregate_id = ua.NodeId(f"{config_id.Identifier}.AggregateConfiguration", node.NamespaceIndex)
    items = [
        _object(config_id, node, ids.HasHistoricalConfiguration, "HA Configuration", config_type),
        _object(aggregate_id, config_id, ids.HasComponent, "AggregateConfiguration", aggregate_type),
        _property(config_id, "Stepped", True, ua.VariantType.Boolean),
        *(_property(aggregate_id, name, value, vtype) for name, value, vtype in _AGGREGATE_CONFIGURATION),
    ]
    results = await server.iserver.isession.add_nodes(items)
    bad = [r.StatusCode for r in results if not r.StatusCode.is_good()]
    if bad:
        raise RuntimeError(f"cannot add the HA Configuration of {node.to_string()}: {bad[0].name}")


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
            cfg.max_values_per_request, ua.VariantType.UInt32
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
