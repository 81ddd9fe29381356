"""OPC 40001-1 MachineryItemState and MachineryOperationMode from a robot's or a PackML unit's own
states (uacell.machinery.model), pure, over the tables read from the Machinery NodeSet."""

from __future__ import annotations

from datetime import date

import pytest
from helpers import official, packml_tables, robotics_tables

from uacell.core.cell_file import Table
from uacell.core.errors import ConfigError
from uacell.core.fsm import Change, Reason
from uacell.machinery.config import parse_machines
from uacell.machinery.model import (
    EXECUTING,
    MAINTENANCE,
    NONE,
    NOT_AVAILABLE,
    NOT_EXECUTING,
    OUT_OF_SERVICE,
    PROCESSING,
    SETUP,
    Facts,
    Machine,
    MachineryTables,
    item_state,
    operation_mode,
    packml_facts,
    robot_facts,
)
from uacell.models import StateTables


@pytest.fixture(scope="module")
def tables() -> MachineryTables:
    return MachineryTables.load(StateTables(official()))


# The mapping as docs/machinery.md states it, state by state.
PACKML_ITEM_STATES = {
    "Idle": NOT_EXECUTING,
    "Starting": EXECUTING,
    "Execute": EXECUTING,
    "Completing": EXECUTING,
    "Complete": NOT_EXECUTING,
    "Resetting": NOT_EXECUTING,
    "Holding": EXECUTING,
    "Held": NOT_EXECUTING,
    "Unholding": EXECUTING,
    "Suspending": EXECUTING,
    "Suspended": NOT_EXECUTING,
    "Unsuspending": EXECUTING,
    "Stopping": NOT_EXECUTING,
    "Stopped": NOT_EXECUTING,
    "Clearing": OUT_OF_SERVICE,
    "Aborting": OUT_OF_SERVICE,
    "Aborted": OUT_OF_SERVICE,
}


def test_every_state_a_packml_unit_can_be_in_has_its_item_state():
    # the unit's state is its innermost active machine's: every state of the three machines that
    # hosts no sub-machine
    t = packml_tables()
    leaves = {s.name for m in (t.base, t.machine, t.execute) for s in m.states.values() if s.submachine is None}
    assert leaves == set(PACKML_ITEM_STATES)
    for state, expected in PACKML_ITEM_STATES.items():
        assert item_state(packml_facts(state, 1)) == expected, state


def test_packml_unit_modes_map_to_operation_modes():
    assert [operation_mode(packml_facts("Idle", m)) for m in (1, 2, 3)] == [PROCESSING, MAINTENANCE, SETUP]
    assert operation_mode(packml_facts("Idle", 0)) == NONE  # Invalid
    assert operation_mode(packml_facts("Idle", 7)) == NONE  # a user-defined mode: not one of Machinery's


def test_a_unit_that_cannot_be_reached_is_not_available_in_no_mode():
    facts = packml_facts("Execute", 1, reachable=False)
    assert (item_state(facts), operation_mode(facts)) == (NOT_AVAILABLE, NONE)


def test_an_unknown_packml_state_is_refused():
    with pytest.raises(ValueError, match="Running"):
        packml_facts("Running", 1)  # hosts Execute: never the unit's state


def test_robot_system_operation_states_map_to_item_states():
    t = robotics_tables()
    assert {s.name for s in t.system_operation.states.values()} == {"Idle", "Ready", "Executing"}
    assert item_state(robot_facts(["Idle"], None)) == NOT_EXECUTING
    assert item_state(robot_facts(["Ready"], None)) == NOT_EXECUTING
    assert item_state(robot_facts(["Executing"], None)) == EXECUTING
    # a robot with two controllers executes when either does
    assert item_state(robot_facts(["Ready", "Executing"], None)) == EXECUTING
    # an active alarm: out of service, also while a controller still executes
    assert item_state(robot_facts(["Executing"], None, alarm=True)) == OUT_OF_SERVICE
    # one controller out of reach: the robot is not available
    assert item_state(robot_facts(["Ready"], None, alarm=True, reachable=False)) == NOT_AVAILABLE


def test_robot_operational_modes_map_to_operation_modes():
    modes = [operation_mode(robot_facts(["Idle"], m)) for m in range(5)]
    # OTHER, MANUAL_REDUCED_SPEED, MANUAL_HIGH_SPEED, AUTOMATIC, AUTOMATIC_EXTERNAL
    assert modes == [NONE, SETUP, SETUP, PROCESSING, PROCESSING]
    assert operation_mode(robot_facts(["Idle"], None)) == PROCESSING  # reports none: uacell runs it
    assert operation_mode(robot_facts(["Idle"], 9)) == NONE
    assert operation_mode(robot_facts(["Idle"], 3, reachable=False)) == NONE
    with pytest.raises(ValueError, match="Running"):
        robot_facts(["Running"], None)


def test_the_tables_come_from_the_nodeset(tables):
    # the StateNumbers OPC 40001-1 gives them (what CurrentState/Number publishes)
    numbers = {s.name: s.number for s in tables.item_state.states.values()}
    assert numbers == {NOT_AVAILABLE: 0, OUT_OF_SERVICE: 1, NOT_EXECUTING: 2, EXECUTING: 3}
    numbers = {s.name: s.number for s in tables.operation_mode.states.values()}
    assert numbers == {NONE: 0, MAINTENANCE: 1, SETUP: 2, PROCESSING: 3}
    # every state reaches every other (and itself) by a transition of its own
    assert len(tables.item_state.transitions) == 16 and len(tables.operation_mode.transitions) == 16


def test_a_machine_takes_the_nodesets_transition_to_each_new_state(tables):
    machine = Machine("Filler1", tables, packml_facts("Idle", 1))
    changes: list[Change] = []
    machine.item_state.listeners.append(changes.append)
    machine.operation_mode.listeners.append(changes.append)
    assert (machine.state, machine.mode) == (NOT_EXECUTING, PROCESSING)

    assert machine.observe(packml_facts("Starting", 1))
    assert not machine.observe(packml_facts("Execute", 1))  # still Executing: no transition, no event
    assert machine.observe(packml_facts("Aborted", 2))
    assert machine.observe(packml_facts("Aborted", 2, reachable=False))
    got = [(c.machine.name, c.transition.name if c.transition else None, c.reason) for c in changes]
    assert got == [
        ("MachineryItemState", "FromNotExecutingToExecuting", Reason.SYSTEM),
        ("MachineryItemState", "FromExecutingToOutOfService", Reason.SYSTEM),
        ("MachineryOperationMode", "FromProcessingToMaintenance", Reason.SYSTEM),
        ("MachineryItemState", "FromOutOfServiceToNotAvailable", Reason.SYSTEM),
        ("MachineryOperationMode", "FromMaintenanceToNone", Reason.SYSTEM),
    ]
    assert (machine.state, machine.mode) == (NOT_AVAILABLE, NONE)
    # each transition's number is the NodeSet's
    assert all(c.transition is not None and c.transition.number is not None for c in changes)


def test_facts_default_to_an_idle_machine_in_no_mode():
    assert (item_state(Facts()), operation_mode(Facts())) == (NOT_EXECUTING, NONE)


# -- [[machines]] --------------------------------------------------------------------------------


def machines(text: str):
    import tomllib

    return parse_machines(Table(tomllib.loads(text), "", "cell.toml"), "machines")


def test_a_machines_entry_reads_its_identification_by_browse_name():
    section = machines(
        """
[[machines]]
name = "Filler1"
manufacturer = "ACME"
serial_number = "F-1"
year_of_construction = 2021
month_of_construction = 5
initial_operation_date = "2021-06-30"
location = "Hall 3"
"""
    )
    (entry,) = section.machines
    assert entry.values == {
        "Manufacturer": "ACME",
        "SerialNumber": "F-1",
        "Location": "Hall 3",
        "YearOfConstruction": 2021,
        "MonthOfConstruction": 5,
        "InitialOperationDate": date(2021, 6, 30),
    }
    assert section.parts() == [] and section.top_names() == []
    assert section.describe({})[0] == "Machines/Filler1  (OPC 40001-1 identification)"


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ('name = "F"\nmonth_of_construction = 13', r"\[machines.F\] month_of_construction: must be within 1..12"),
        ('name = "F"\nyear_of_construction = 70000', r"year_of_construction: must be within 1..65535"),
        ('name = "F"\nyear_of_construction = "2021"', r"year_of_construction: must be an integer"),
        ('name = "F"\ninitial_operation_date = "30.6.2021"', r"initial_operation_date: '30.6.2021' is not a date"),
        ('name = "F"\nlocaton = "x"', r"locaton: unknown key; did you mean 'location'\?"),
        ('manufacturer = "x"', r"name: is missing"),
    ],
)
def test_a_bad_machines_entry_is_refused_naming_its_key(entry, message):
    with pytest.raises(ConfigError, match=message):
        machines(f"[[machines]]\n{entry}\n")


def test_a_machine_described_twice_is_refused():
    with pytest.raises(ConfigError, match="machine 'F' is declared twice"):
        machines('[[machines]]\nname = "F"\n[[machines]]\nname = "F"\n')
