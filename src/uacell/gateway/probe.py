"""``uacell config check --connect``: try every endpoint and tag the gateway drivers of a cell name,
and say for each what was found (docs/equipment.md, "Gateway"); and, with or without ``--connect``
(and before ``uacell serve`` starts), ``shared_settings``: parts that share one connection to a PLC
must agree on its settings."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from asyncua import ua

from uacell.core.cell_file import Part
from uacell.core.drivers import factory_of
from uacell.gateway.errors import CommunicationError, DashboardError
from uacell.gateway.opcua_link import LinkOptions, link_options, new_client, resolve_address
from uacell.gateway.opcua_robot import robot_addresses
from uacell.gateway.packtags import PackTagsMapError, resolve
from uacell.gateway.pool import shared_conflict

# The Modbus, S7 and Logix transports are imported by the probes that use them: each needs its
# library, an optional extra (uacell.core.extras) that a cell without such a part may not have installed.

# The drivers it knows how to probe, by their factories (uacell.core.drivers, the one registry).
MODBUS = factory_of("modbus-signals")
PACKTAGS = factory_of("opcua-packtags")
MODBUS_PACKTAGS = factory_of("modbus-packtags")
UR = factory_of("ur-dashboard")
OPCUA_SIGNALS = factory_of("opcua-signals")
S7_PACKTAGS = factory_of("s7-packtags")
LOGIX_PACKTAGS = factory_of("logix-packtags")
_BUILTIN = {ua.VariantType.Int32: "Int32", ua.VariantType.Boolean: "Boolean", ua.VariantType.Float: "Float"}


@dataclass(frozen=True)
class Row:
    part: str
    endpoint: str
    tag: str
    result: str
    ok: bool


def gateway_parts(parts: list[tuple[str, Part]]) -> Iterator[tuple[str, str, Mapping[str, Any]]]:
    """(part path, driver factory, settings) of every part whose equipment is a shipped driver."""

    def walk(part: Part, path: str) -> Iterator[tuple[str, str, Mapping[str, Any]]]:
        here = f"{path}.{part.name}" if path else part.name
        equipment = getattr(part.spec, "equipment", "")
        if equipment in PROBES:
            yield here, equipment, getattr(part.spec, "settings", {})
        for child in part.children:
            yield from walk(child, here)

    for _root, part in parts:
        yield from walk(part, "")


def _modbus_connection(part: str, driver: str, settings: Mapping[str, Any]) -> tuple[str, int, float]:
    """(host, port, timeout) of a Modbus driver's connection; ValueError or TypeError if the settings are wrong."""
    from uacell.gateway.packml_modbus import where  # the 'modbus' extra: its factory was loaded

    if driver == MODBUS_PACKTAGS:
        w = where(part, settings)
        return w.host, w.port, w.timeout
    return str(settings.get("host", "")), int(settings.get("port", 502)), float(settings.get("timeout", 1.0))


def _modbus_endpoint(host: str, port: int) -> str:
    from uacell.gateway.modbus import endpoint_name

    return endpoint_name(host, port)


def shared_settings(parts: list[tuple[str, Part]]) -> list[str]:
    """Parts on one Modbus endpoint (host and port) share one connection, which has one ``timeout``:
    a line for every part that gives it another than the first part there did (naming both)."""
    first: dict[tuple[str, int], tuple[str, float]] = {}
    problems = []
    for path, driver, settings in gateway_parts(parts):
        if driver not in (MODBUS, MODBUS_PACKTAGS):
            continue
        try:
            host, port, timeout = _modbus_connection(path, driver, settings)
        except (ValueError, TypeError):
            continue  # the driver says what is wrong when it starts
        seen = first.setdefault((host, port), (path, timeout))
        if seen[1] != timeout:
            problems.append(shared_conflict(_modbus_endpoint(host, port), "timeout", seen, (path, timeout)))
    return problems


async def probe_packtags(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    endpoint = str(settings.get("endpoint", ""))
    try:
        options = link_options(part, settings)
    except ValueError as e:
        return [Row(part, endpoint, "(settings)", str(e), False)]
    try:
        tags = resolve(
            part,
            str(settings.get("prefix", "")),
            {str(k): str(v) for k, v in dict(settings.get("map", {})).items()},
            parameters=int(settings.get("parameters", 5)),
            alarms=int(settings.get("alarms", 0)),
        )
    except PackTagsMapError as e:
        return [Row(part, endpoint, "(map)", str(e), False)]
    wanted = {key: (tag.address, tag.type_name) for key, tag in tags.items()}
    return await _read_opcua(part, endpoint, options, timeout, wanted)


async def _read_opcua(
    part: str, endpoint: str, options: LinkOptions, timeout: float, wanted: Mapping[str, tuple[str, str | None]]
) -> list[Row]:
    """Connect as the driver would and read each ``key: (address, expected type or None)`` once: a row
    per key, found and typed as expected (any type where None), or what is wrong."""
    try:
        client = await new_client(options, timeout)
        await asyncio.wait_for(client.connect(), timeout)
    except Exception as e:
        return [Row(part, endpoint, "(endpoint)", f"unreachable: {e or type(e).__name__}", False)]
    rows = []
    try:
        for key, (address, expected) in wanted.items():
            try:
                node = client.get_node(await resolve_address(client, address))
                dv = await node.read_data_value(raise_on_bad_status=False)
            except Exception as e:
                rows.append(Row(part, endpoint, key, f"{address}: {e}", False))
                continue
            if not dv.StatusCode.is_good():
                rows.append(Row(part, endpoint, key, f"{address}: {dv.StatusCode.name}", False))
                continue
            found = _BUILTIN.get(dv.Value.VariantType, dv.Value.VariantType.name) if dv.Value else "null"
            ok = expected is None or found == expected
            value = dv.Value.Value if dv.Value else None
            text = f"{found} = {value!r}" if ok else f"{found} = {value!r}, expected {expected}"
            rows.append(Row(part, endpoint, key, text, ok))
    finally:
        await client.disconnect()
    return rows


async def probe_modbus(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    from uacell.gateway.modbus import ModbusConnection, endpoint_name
    from uacell.gateway.modbus_robot import parse_motion, signal_tags, used_tags

    host, port, unit = str(settings.get("host", "")), int(settings.get("port", 502)), int(settings.get("unit", 1))
    endpoint = f"{endpoint_name(host, port)} unit {unit}"
    try:
        overrides = {k: (str(v[0]), int(v[1]), str(v[2])) for k, v in dict(settings.get("map", {})).items()}
        by_name = any(isinstance(v, str) for v in dict(settings.get("programs", {})).values())
        motion = parse_motion(settings["motion"]) if "motion" in settings else None
        # what the driver reads and writes: the name signals only when asked for, the safety signals
        # only when mapped, the axes' registers (six axes: the probe does not know the motion device)
        tags = used_tags(signal_tags(overrides), by_name, list(overrides), motion, 6)
    except (ValueError, TypeError, IndexError) as e:
        return [Row(part, endpoint, "(map)", str(e), False)]
    conn = ModbusConnection(host, port, timeout=timeout)
    try:
        if not await conn.connect():
            return [Row(part, endpoint, "(endpoint)", "unreachable", False)]
        rows = []
        for name, tag in tags.items():
            where = f"{tag.table} {tag.address}"
            try:
                rows.append(Row(part, endpoint, name, f"{where} = {await conn.read(tag, unit)!r}", True))
            except CommunicationError as e:
                rows.append(Row(part, endpoint, name, f"{where}: {e}", False))
        return rows
    finally:
        conn.close()


async def probe_modbus_packtags(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    from uacell.gateway.modbus import ModbusConnection
    from uacell.gateway.packml_modbus import Point, where

    try:
        w = where(part, settings)
    except ValueError as e:
        return [Row(part, f"modbus://{settings.get('host', '')}", "(settings)", str(e), False)]
    conn = ModbusConnection(w.host, w.port, timeout=timeout)
    try:
        if not await conn.connect():
            return [Row(part, w.endpoint, "(endpoint)", "unreachable", False)]
        rows = []
        for key, tag in w.tags.items():
            point = Point.parse(tag.address)
            try:
                value = await conn.read(point.tag, point.device)
                rows.append(Row(part, w.endpoint, key, f"{point} = {value!r}", True))
            except CommunicationError as e:
                rows.append(Row(part, w.endpoint, key, f"{point}: {str(e).rpartition(': ')[2]}", False))
        return rows
    finally:
        conn.close()


async def probe_ur(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    """The Dashboard Server (its welcome, robot mode, remote control, the configured program files are
    not checked: PolyScope 5 cannot list them) and UR's Modbus registers the driver reads."""
    from uacell.gateway.modbus import ModbusConnection, endpoint_name
    from uacell.gateway.ur_link import JOINT_REGISTERS, STATE_REGISTERS, TURN_REGISTERS, Dashboard

    host = str(settings.get("host", ""))
    port, modbus_port = int(settings.get("port", 29999)), int(settings.get("modbus_port", 502))
    rows: list[Row] = []
    dashboard = Dashboard(host, port, timeout)
    where = f"dashboard {host}:{port}"
    try:
        await dashboard.connect()
        for command in ("PolyscopeVersion", "robotmode", "is in remote control"):
            rows.append(Row(part, where, command, await dashboard.ask(command), True))
    except DashboardError as e:
        rows.append(Row(part, where, "(endpoint)", f"unreachable: {str(e).rpartition(': ')[2]}", False))
    finally:
        await dashboard.aclose()
    conn = ModbusConnection(host, modbus_port, timeout=timeout)
    where = f"{endpoint_name(host, modbus_port)} unit {int(settings.get('unit', 1))}"
    try:
        if not await conn.connect():
            return [*rows, Row(part, where, "(endpoint)", "unreachable", False)]
        for first, count in (STATE_REGISTERS, JOINT_REGISTERS, TURN_REGISTERS):
            name = f"holding {first}..{first + count - 1}"
            try:
                values = await conn.read_block("holding", first, count, int(settings.get("unit", 1)))
                rows.append(Row(part, where, name, f"= {list(values)}", True))
            except CommunicationError as e:
                rows.append(Row(part, where, name, str(e).rpartition(": ")[2], False))
    finally:
        conn.close()
    return rows


async def probe_opcua_signals(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    """Every signal variable (and axis variable) the opcua-signals driver uses: found, and its value."""
    endpoint = str(settings.get("endpoint", ""))
    try:
        options = link_options(part, settings)
        used = robot_addresses(settings)
    except ValueError as e:
        return [Row(part, endpoint, "(settings)", str(e), False)]
    wanted = {key: (address, None) for key, address in used.items()}
    return await _read_opcua(part, endpoint, options, timeout, wanted)


async def probe_s7_packtags(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    from uacell.gateway.packml_s7 import S7Connection
    from uacell.gateway.packml_s7 import where as s7_where
    from uacell.gateway.s7 import S7Address

    try:
        w = s7_where(part, settings)
    except ValueError as e:
        return [Row(part, f"s7://{settings.get('host', '')}", "(settings)", str(e), False)]
    conn = S7Connection(w.host, w.port, w.rack, w.slot, timeout)
    if not await conn.connect():
        return [Row(part, w.endpoint, "(endpoint)", "unreachable", False)]
    rows = []
    try:
        for key, tag in w.tags.items():
            address = S7Address.parse(tag.address)
            try:
                block = await conn.read(address.db, address.byte, address.size)
                rows.append(Row(part, w.endpoint, key, f"{address} = {address.decode(block, address.byte)!r}", True))
            except CommunicationError as e:
                rows.append(Row(part, w.endpoint, key, f"{address}: {str(e).rpartition(': ')[2]}", False))
                if not conn.connected:
                    break
        return rows
    finally:
        await conn.close()


async def probe_logix_packtags(part: str, settings: Mapping[str, Any], timeout: float = 3.0) -> list[Row]:
    from uacell.gateway.packml_logix import LogixConnection
    from uacell.gateway.packml_logix import where as logix_where

    try:
        w = logix_where(part, settings)
    except ValueError as e:
        return [Row(part, f"logix://{settings.get('host', '')}", "(settings)", str(e), False)]
    conn = LogixConnection(w.host, w.port, w.slot, timeout)
    if not await conn.connect():
        return [Row(part, w.endpoint, "(endpoint)", "unreachable", False)]
    rows = []
    try:
        for key, tag in w.tags.items():
            try:
                (value,) = await conn.read([tag.address])
            except CommunicationError as e:
                rows.append(Row(part, w.endpoint, key, f"{tag.address}: {str(e).rpartition(': ')[2]}", False))
                if not conn.connected:
                    break
                continue
            found = {bool: "Boolean", int: "Int32", float: "Float"}.get(type(value), type(value).__name__)
            ok = found == tag.type_name or (found == "Int32" and tag.type_name == "Float")
            text = f"{tag.address} = {value!r}" if ok else f"{tag.address} = {value!r}, expected {tag.type_name}"
            rows.append(Row(part, w.endpoint, key, text, ok))
        return rows
    finally:
        await asyncio.to_thread(conn.close)


PROBES = {
    OPCUA_SIGNALS: probe_opcua_signals,
    MODBUS: probe_modbus,
    PACKTAGS: probe_packtags,
    MODBUS_PACKTAGS: probe_modbus_packtags,
    UR: probe_ur,
    S7_PACKTAGS: probe_s7_packtags,
    LOGIX_PACKTAGS: probe_logix_packtags,
}


async def probe(parts: list[tuple[str, Part]]) -> list[Row]:
    rows: list[Row] = []
    for path, driver, settings in gateway_parts(parts):
        rows += await PROBES[driver](path, settings)
    return rows


def table(rows: list[Row]) -> list[str]:
    """The rows as aligned text lines (part, endpoint, tag, what was found)."""
    if not rows:
        return ["connect: no part uses a gateway driver"]
    head = ("part", "endpoint", "tag", "found")
    cells = [head, *((r.part, r.endpoint, r.tag, r.result if r.ok else f"PROBLEM: {r.result}") for r in rows)]
    widths = [max(len(c[i]) for c in cells) for i in range(3)]
    return ["  ".join([*(c[i].ljust(widths[i]) for i in range(3)), c[3]]).rstrip() for c in cells]
