"""``toolkit.ValueWriter``: what it stores is what asyncua's own write stores, and whoever watches a
value (a subscription, history: a data change callback) is told, whichever way the write goes."""

from __future__ import annotations

from collections.abc import AsyncIterator
from datetime import UTC, datetime

import pytest
import pytest_asyncio
from asyncua import Server, ua

from uacell.ua.toolkit import ValueWriter

module_loop = pytest.mark.asyncio(loop_scope="module")
_A = ua.AttributeIds


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server() -> AsyncIterator[Server]:
    server = Server()
    await server.init()
    yield server


async def _variable(server: Server, name: str, value: object, vtype: ua.VariantType) -> ua.NodeId:
    node = await server.nodes.objects.add_variable(ua.NodeId(name, 1), name, ua.Variant(value, vtype))
    nodeid: ua.NodeId = node.nodeid
    return nodeid


def _told(server: Server, nodeid: ua.NodeId) -> list[ua.DataValue]:
    told: list[ua.DataValue] = []

    async def callback(_handle: int, dv: ua.DataValue) -> None:
        told.append(dv)

    server.iserver.aspace.add_datachange_callback(nodeid, _A.Value, callback)
    return told


@module_loop
async def test_a_value_nobody_watches_is_stored_as_asyncuas_write_stores_it(server: Server) -> None:
    aspace = server.iserver.aspace
    mine = await _variable(server, "Mine", 1.0, ua.VariantType.Double)
    theirs = await _variable(server, "Theirs", 1.0, ua.VariantType.Double)
    writer = ValueWriter(aspace, lambda _datatype: None)
    before = datetime.now(UTC)
    await writer.write(mine, 2.5, ua.VariantType.Double)
    now = datetime.now(UTC)
    await aspace.write_attribute_value(
        theirs, _A.Value, ua.DataValue(ua.Variant(2.5, ua.VariantType.Double), SourceTimestamp=now, ServerTimestamp=now)
    )
    stored, expected = aspace.read_attribute_value(mine, _A.Value), aspace.read_attribute_value(theirs, _A.Value)
    assert (stored.Value, stored.StatusCode) == (expected.Value, expected.StatusCode)
    assert stored.SourceTimestamp is not None and stored.SourceTimestamp >= before
    assert stored.ServerTimestamp == stored.SourceTimestamp
    # a Bad status: null Value, the status, stamped; as asyncua's write makes it
    await writer.write_status(mine, ua.StatusCode(ua.StatusCodes.BadStateNotActive))
    status_only = aspace.read_attribute_value(mine, _A.Value)
    assert status_only.StatusCode == ua.StatusCode(ua.StatusCodes.BadStateNotActive)
    assert status_only.Value == ua.Variant(None, ua.VariantType.Null)
    assert status_only.SourceTimestamp is not None and status_only.SourceTimestamp >= now


@module_loop
async def test_a_value_of_another_type_is_left_to_asyncua_which_refuses_it(server: Server) -> None:
    aspace = server.iserver.aspace
    node = await _variable(server, "Typed", 1.0, ua.VariantType.Double)
    writer = ValueWriter(aspace, lambda _datatype: None)
    await writer.write(node, "text", ua.VariantType.String)
    assert aspace.read_attribute_value(node, _A.Value).Value == ua.Variant(1.0, ua.VariantType.Double)


@module_loop
async def test_whoever_watches_a_value_is_told_of_every_write(server: Server) -> None:
    aspace = server.iserver.aspace
    node = await _variable(server, "Watched", 1.0, ua.VariantType.Double)
    told = _told(server, node)
    writer = ValueWriter(aspace, lambda _datatype: None)
    await writer.write(node, 3.0, ua.VariantType.Double)
    await writer.write_status(node, ua.StatusCode(ua.StatusCodes.BadStateNotActive))
    assert [dv.Value.Value for dv in told] == [3.0, None]
    assert told[1].StatusCode == ua.StatusCode(ua.StatusCodes.BadStateNotActive)
    assert aspace.read_attribute_value(node, _A.Value) is told[1]
