"""The PackML rules the tables cannot say, free of OPC UA: the machines' names, the entry states
(decision 23), the commands a unit mode disables (decision 26), the ISA-TR88 command numbers, the
three NodeSet tables (``PackMLTables``) and the shortest way between two states (``path``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.models.tables import FsmTable, TableLoader
from uacell.packml.types import ProductionMaintenanceModeEnum

BASE = "BaseStateMachine"
MACHINE = "MachineState"
EXECUTE = "ExecuteState"
UNIT = None  # machine_name of the unit's own methods (SetUnitMode, ...) in executable()/command()
UNIT_METHODS = ("SetUnitMode", "SetMachSpeed", "SetProduct", "SetParameter", "RemoteCommand", "SetInterlock")

Mode = ProductionMaintenanceModeEnum
COMPLETE = "complete"  # a step that ends an acting state (PackMLTables.steps, path)
# Decision 23: the sub-state a machine is entered at when its parent enters the hosting state.
ENTRY_STATE = {MACHINE: "Clearing", EXECUTE: "Resetting"}
# Decision 26.
MODE_DISABLED: dict[int, frozenset[str]] = {
    Mode.MAINTENANCE: frozenset({"Suspend"}),
    Mode.MANUAL: frozenset({"Start", "Suspend", "Hold", "ToComplete"}),
}
SET_UNIT_MODE_STATES = frozenset({"Stopped", "Idle", "Aborted"})
# uacell's rule: products and parameters change only while no job runs (between Start and Complete).
JOB_STATES = frozenset(
    {"Starting", "Execute", "Completing", "Holding", "Held", "Unholding", "Suspending", "Suspended", "Unsuspending"}
)
# The ISA-TR88 command numbers (PackTags Command.CntrlCmd): uacell's one table of them (the PLC gateway
# writes them too).
TR88_COMMANDS: dict[str, int] = {
    "Reset": 1,
    "Start": 2,
    "Stop": 3,
    "Hold": 4,
    "Unhold": 5,
    "Suspend": 6,
    "Unsuspend": 7,
    "Abort": 8,
    "Clear": 9,
    "Complete": 10,
}
# StopReason.ID for a commanded stop: the ISA-TR88 command number (Stop 3, Hold 4, Suspend 6, Abort 8).
STOP_COMMAND_IDS = {name: TR88_COMMANDS[name] for name in ("Stop", "Hold", "Suspend", "Abort")}


@dataclass(frozen=True)
class PackMLTables:
    """The three PackML state-machine tables, handed to ``PackMLUnit`` by whoever knows the NodeSets."""

    base: FsmTable
    machine: FsmTable
    execute: FsmTable

    @classmethod
    def load(cls, tables: TableLoader) -> PackMLTables:
        loaded = cls(
            base=tables("PackML", "PackMLBaseStateMachineType"),
            machine=tables("PackML", "PackMLMachineStateMachineType"),
            execute=tables("PackML", "PackMLExecuteStateMachineType"),
        )
        loaded.base.check_names(("Cleared",))
        loaded.machine.check_names(("Stopped", ENTRY_STATE[MACHINE]))
        loaded.execute.check_names(("Idle", "Execute", ENTRY_STATE[EXECUTE], *JOB_STATES))
        return loaded

    def steps(self) -> dict[str, list[tuple[str, str]]]:
        """Each innermost state's steps, from the NodeSet's transitions: (the method that causes a
        transition from it or from a state hosting it, the innermost state that leads to) and, for an
        acting state, (``COMPLETE``, where it ends). A transition into a state hosting a sub-machine
        leads to that machine's entry state (decision 23)."""
        tables = {BASE: self.base, MACHINE: self.machine, EXECUTE: self.execute}

        def entry(table: FsmTable, state: str) -> str:
            sub = table.states[state].submachine
            return entry(tables[sub], ENTRY_STATE[sub]) if sub in tables else state

        def leaves(table: FsmTable, state: str) -> list[str]:
            sub = table.states[state].submachine
            if sub not in tables:
                return [state]
            return [leaf for inner in tables[sub].states for leaf in leaves(tables[sub], inner)]

        out: dict[str, list[tuple[str, str]]] = {
            name: [] for t in tables.values() for name, info in t.states.items() if info.submachine not in tables
        }
        for table in tables.values():
            for t in table.transitions.values():
                for leaf in leaves(table, t.from_state):
                    out[leaf].append((t.causes[0] if t.causes else COMPLETE, entry(table, t.to_state)))
        return out


def path(steps: Mapping[str, Sequence[tuple[str, str]]], current: str, target: str) -> list[tuple[str, str]]:
    """The fewest ``steps`` (``PackMLTables.steps``) from the innermost state ``current`` to
    ``target``; [] when they are the same or there is no way."""
    if current == target or current not in steps or target not in steps:
        return []
    came: dict[str, tuple[str, tuple[str, str]]] = {}
    queue = [current]
    for state in queue:  # breadth first: the queue grows while it is walked
        for step in steps[state]:
            following = step[1]
            if following in came or following == current:
                continue
            came[following] = (state, step)
            if following == target:
                found = []
                while following != current:
                    before, taken = came[following]
                    found.append(taken)
                    following = before
                return found[::-1]
            queue.append(following)
    return []


def hosting(states: Iterable[Any], submachine: str) -> str:
    return next(str(s.name) for s in states if s.submachine == submachine)
