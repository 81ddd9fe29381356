"""What a machine is in OPC 40001-1 terms, derived from what its own companion says of it (pure).

A robot (its MotionDeviceSystem) and a PackML unit are machines. What each companion knows of its
part is reduced to ``Facts`` (``packml_facts``, ``robot_facts``); the two Machinery state machines
follow the facts (``item_state``, ``operation_mode``). The tables are read from the Machinery NodeSet
(``MachineryTables.load``), never typed here: a ``Machine`` only moves its machines to a state and the
table finds the transition, which the state-machine binding announces with its TransitionEvent.

The mapping tables and their reasons are in docs/machinery.md and docs/decisions.md.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from uacell.core.fsm import Reason, StateMachine
from uacell.models.tables import FsmTable, TableLoader

MACHINERY = "Machinery"  # the model key of the Machinery NodeSet
ITEM_STATE_TYPE = "MachineryItemState_StateMachineType"
OPERATION_MODE_TYPE = "MachineryOperationModeStateMachineType"
ITEM_STATE, OPERATION_MODE = "MachineryItemState", "MachineryOperationMode"  # their default BrowseNames

# MachineryItemState_StateMachineType
NOT_AVAILABLE, OUT_OF_SERVICE, NOT_EXECUTING, EXECUTING = "NotAvailable", "OutOfService", "NotExecuting", "Executing"
# MachineryOperationModeStateMachineType
NONE, MAINTENANCE, SETUP, PROCESSING = "None", "Maintenance", "Setup", "Processing"

# PackML (OPC 30050) states in which the unit does what it is for: Execute, and the acting states
# that lead into, continue or wind down production (the equipment is moving product in each).
PACKML_EXECUTING = frozenset(
    {"Starting", "Execute", "Completing", "Holding", "Unholding", "Suspending", "Unsuspending"}
)
# PackML states in which the unit cannot work until someone clears it: the abort branch.
PACKML_OUT_OF_SERVICE = frozenset({"Aborting", "Aborted", "Clearing"})
# Every other PackML state (Idle, Resetting, Stopping, Stopped, Held, Suspended, Complete) is NotExecuting.
PACKML_NOT_EXECUTING = frozenset({"Idle", "Resetting", "Stopping", "Stopped", "Held", "Suspended", "Complete"})

# PackML UnitMode (ProductionMaintenanceModeEnum) -> MachineryOperationMode; other modes -> None.
PACKML_MODES = {1: PROCESSING, 2: MAINTENANCE, 3: SETUP}  # Produce, Maintenance, Manual

# Robotics OperationalModeEnumeration (OPC 40010-1) -> MachineryOperationMode.
OTHER, MANUAL_REDUCED_SPEED, MANUAL_HIGH_SPEED, AUTOMATIC, AUTOMATIC_EXTERNAL = range(5)
ROBOT_MODES = {
    OTHER: NONE,
    MANUAL_REDUCED_SPEED: SETUP,  # T1: teaching, trying out
    MANUAL_HIGH_SPEED: SETUP,  # T2: trying out at full speed
    AUTOMATIC: PROCESSING,
    AUTOMATIC_EXTERNAL: PROCESSING,
}
# Robotics SystemOperation states (OPC 40010-1 v1.02).
ROBOT_EXECUTING = "Executing"
ROBOT_STATES = ("Idle", "Ready", "Executing")


@dataclass(frozen=True)
class Facts:
    """What a machine's own companion says of it, as far as OPC 40001-1 cares."""

    reachable: bool = True  # False: uacell cannot reach the equipment (a gateway's communication loss)
    out_of_service: bool = False  # it cannot work until someone acts (an abort, an active alarm)
    executing: bool = False  # it does what it is for
    mode: str = NONE  # a MachineryOperationMode state


def packml_facts(state: str, unit_mode: int, reachable: bool = True) -> Facts:
    """A PackML unit's facts: its TR88 state (the innermost active machine's), its UnitModeCurrent
    and whether its equipment is reachable."""
    if state not in PACKML_EXECUTING | PACKML_OUT_OF_SERVICE | PACKML_NOT_EXECUTING:
        raise ValueError(f"{state!r} is not a PackML state")
    return Facts(
        reachable=reachable,
        out_of_service=state in PACKML_OUT_OF_SERVICE,
        executing=state in PACKML_EXECUTING,
        mode=PACKML_MODES.get(unit_mode, NONE),
    )


def robot_facts(
    system_states: Iterable[str], operational_mode: int | None, *, alarm: bool = False, reachable: bool = True
) -> Facts:
    """A robot's facts: the SystemOperation states of its controllers, its OperationalMode (None: its
    equipment reports none, taken as AUTOMATIC: uacell starts the programs itself), whether one of its
    controllers has an active alarm and whether every controller's equipment is reachable."""
    states = list(system_states)
    unknown = sorted(set(states) - set(ROBOT_STATES))
    if unknown:
        raise ValueError(f"{unknown[0]!r} is not a SystemOperation state")
    mode = AUTOMATIC if operational_mode is None else operational_mode
    return Facts(
        reachable=reachable,
        out_of_service=alarm,
        executing=ROBOT_EXECUTING in states,
        mode=ROBOT_MODES.get(mode, NONE),
    )


def item_state(facts: Facts) -> str:
    """MachineryItemState from the facts: not reachable first (nothing else is known then), then out of
    service, then executing or not."""
    if not facts.reachable:
        return NOT_AVAILABLE
    if facts.out_of_service:
        return OUT_OF_SERVICE
    return EXECUTING if facts.executing else NOT_EXECUTING


def operation_mode(facts: Facts) -> str:
    """MachineryOperationMode from the facts: None while the equipment cannot be reached (its mode is
    not known then), else the companion's mode mapped."""
    return facts.mode if facts.reachable else NONE


@dataclass(frozen=True)
class MachineryTables:
    """The two Machinery state-machine tables, read from the NodeSet."""

    item_state: FsmTable
    operation_mode: FsmTable

    @classmethod
    def load(cls, tables: TableLoader) -> MachineryTables:
        loaded = cls(tables(MACHINERY, ITEM_STATE_TYPE), tables(MACHINERY, OPERATION_MODE_TYPE))
        loaded.item_state.check_names((NOT_AVAILABLE, OUT_OF_SERVICE, NOT_EXECUTING, EXECUTING))
        loaded.operation_mode.check_names((NONE, MAINTENANCE, SETUP, PROCESSING))
        return loaded


class Machine:
    """One machine's MachineryItemState and MachineryOperationMode, following its facts."""

    def __init__(self, name: str, tables: MachineryTables, facts: Facts) -> None:
        self.name = name
        self.facts = facts
        self.item_state = StateMachine(ITEM_STATE, tables.item_state, item_state(facts))
        self.operation_mode = StateMachine(OPERATION_MODE, tables.operation_mode, operation_mode(facts))

    @property
    def state(self) -> str:
        return self.item_state.current

    @property
    def mode(self) -> str:
        return self.operation_mode.current

    def observe(self, facts: Facts) -> bool:
        """Follow ``facts``: each machine whose state they change takes the NodeSet's transition to it
        (LastTransitionReason System: the machine's own companion moved it). True if one moved."""
        self.facts = facts
        moved = False
        for machine, wanted in ((self.item_state, item_state(facts)), (self.operation_mode, operation_mode(facts))):
            if machine.current != wanted:
                machine.move(wanted, Reason.SYSTEM)
                moved = True
        return moved
