"""Optional equipment capabilities are Protocols checked with isinstance (uacell.core.capabilities and the
companions' equipment modules): what a unit and a machine make of equipment that has them, and of
equipment that has not."""

from __future__ import annotations

import pytest
from helpers import packml_tables

from uacell.core.capabilities import Identified, Reachable, reachable
from uacell.core.errors import CallError
from uacell.machinery.sources import UnitSource
from uacell.packml import PackMLUnit
from uacell.packml.equipment import CommandForwarder, EquipmentBase, NamedConditions


class Plain(EquipmentBase):
    pass


class Gateway(EquipmentBase):
    """What a gateway driver has beyond PackMLEquipment: its PLC's reachability, its nameplate."""

    def __init__(self) -> None:
        super().__init__()
        self.reachable = True
        self.identification = {"Manufacturer": "ACME", "SerialNumber": "SN-42", "Model": None}


def test_equipment_without_a_capability_is_reachable_and_reports_nothing() -> None:
    equipment = Plain()
    assert not isinstance(equipment, Reachable | Identified | CommandForwarder | NamedConditions)
    unit = PackMLUnit(equipment, tables=packml_tables())
    assert unit.reachable is True
    assert UnitSource(unit).facts().reachable is True
    assert UnitSource(unit).identification() == {}


def test_a_unit_and_its_machine_follow_what_the_equipment_reports() -> None:
    equipment = Gateway()
    assert isinstance(equipment, Reachable) and isinstance(equipment, Identified)
    unit = PackMLUnit(equipment, tables=packml_tables())
    source = UnitSource(unit)
    assert source.identification() == {"Manufacturer": "ACME", "SerialNumber": "SN-42"}  # None left out
    assert unit.reachable is True and source.facts().reachable is True
    equipment.reachable = False  # the PLC went away
    assert unit.reachable is False and source.facts().reachable is False
    with pytest.raises(CallError):
        unit.check_reachable()


class _Raising:
    """A ``reachable`` property that raises AttributeError: hasattr (so isinstance) says it is not there."""

    @property
    def reachable(self) -> bool:
        raise AttributeError("not yet connected")


class _Property:
    def __init__(self, value: object) -> None:
        self._value = value

    @property
    def reachable(self) -> object:
        return self._value


@pytest.mark.parametrize(
    "equipment",
    [None, object(), Plain(), Gateway(), _Raising(), _Property(False), _Property(True), _Property(0), _Property("")],
    ids=["none", "object", "plain", "gateway", "raising", "false", "true", "zero", "empty"],
)
def test_reachable_answers_what_the_protocol_check_answers(equipment: object) -> None:
    expected = bool(equipment.reachable) if isinstance(equipment, Reachable) else True
    assert reachable(equipment) is expected


def test_a_gateway_that_loses_its_plc_is_unreachable() -> None:
    gateway = Gateway()
    assert reachable(gateway) is True
    gateway.reachable = False
    assert reachable(gateway) is False
