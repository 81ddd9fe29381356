"""The ``opcua-packtags`` driver: a PackML unit in a PLC whose PackTags the PLC serves over its own
OPC UA server (docs/equipment.md, "Gateway"; the unit itself is ``packml_plc.PackTagsUnit``).

    [[packml_units]]
    name = "Capper"
    equipment = { driver = "opcua-packtags", endpoint = "opc.tcp://10.0.0.5:4840/", prefix = "ns=3;s=Capper.PackTags" }
"""

from __future__ import annotations

from typing import Any

from uacell.gateway import DriverSettings
from uacell.gateway.opcua_link import LINK_SETTINGS, link_options, link_pool, shared_link
from uacell.gateway.packml_plc import UNIT_SETTINGS, PackTagsUnit, start_unit
from uacell.gateway.packtags import PackTagsMapError, resolve

SETTINGS = (*LINK_SETTINGS, "prefix", *UNIT_SETTINGS)
POOL = link_pool()


async def opcua_packtags(spec: Any) -> PackTagsUnit:
    """The equipment factory of the ``opcua-packtags`` driver."""
    settings = DriverSettings("opcua-packtags", spec.part, spec.settings, SETTINGS)
    options = link_options(spec.part, settings.raw)
    try:
        tags = resolve(
            spec.part,
            str(settings.get("prefix", "")),
            {str(k): str(v) for k, v in dict(settings.get("map", {})).items()},
            parameters=int(settings.get("parameters", 5)),
            alarms=int(settings.get("alarms", 0)),
        )
    except PackTagsMapError as e:
        raise ValueError(str(e)) from None
    return await start_unit(spec.part, shared_link(POOL, options, spec.part), tags, settings.raw, POOL.release)
