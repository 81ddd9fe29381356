"""PackML unit driver conformance: run it against your equipment factory before you serve it.

    UACELL_UNIT_FACTORY=mydriver:make_filler UACELL_SETTINGS='address = "10.0.0.7"' \
        pytest --pyargs uacell.packml.conformance

The unit is reset, started, produces, and is stopped, each acting state completed by the driver, as
the server's model drives it (docs/equipment.md). It needs the official NodeSets (``uacell models
fetch``); ``UACELL_CONFORMANCE_TIMEOUT`` bounds each operation (default 60 s).
"""

from __future__ import annotations

import asyncio
import inspect

from uacell.core.conformance_kit import factory, run, settings
from uacell.core.equipment_factory import EquipmentSpec, make_equipment


# --- PackML units --------------------------------------------------------------------------------
def test_unit_completes_its_acting_states_and_produces() -> None:
    from uacell.core.companion import models_of
    from uacell.models import StateTables, official_models
    from uacell.packml.companion import PACKML_COMPANION
    from uacell.packml.equipment import PackMLEquipment
    from uacell.packml.model import EXECUTE, MACHINE, PackMLTables, PackMLUnit

    async def check() -> None:
        spec = EquipmentSpec("Conformance", settings())
        equipment = await make_equipment(factory("UACELL_UNIT_FACTORY"), spec, PackMLEquipment)
        unit = PackMLUnit(
            equipment,
            name="Conformance",
            tables=PackMLTables.load(StateTables(official_models(models_of([PACKML_COMPANION])))),
            mach_speed=600.0,
        )
        ticking = asyncio.ensure_future(unit.run(0.02))

        async def reach(state: str) -> None:
            while unit.state != state:
                await asyncio.sleep(0.02)

        try:
            unit.command(MACHINE, "Reset")
            await reach("Idle")
            unit.command(EXECUTE, "Start", [])
            await reach("Execute")
            while unit.admin.prod_processed_count[0].count < 1:
                await asyncio.sleep(0.02)
            unit.command(MACHINE, "Stop")
            await reach("Stopped")
        finally:
            ticking.cancel()
            await asyncio.gather(ticking, return_exceptions=True)
            unit.close()
            if inspect.isawaitable(unit.equipment_closed):  # a driver's close() may be a coroutine
                await unit.equipment_closed

    run(check)
