"""The interface between the PackML model and the equipment behind it.

The model (``PackMLUnit``) owns every rule; the equipment only does the physical work. It gets one
hook per acting state and per unit command, and reports back through the ``UnitPort`` it was given
in ``attach``: an acting state is done (``state_complete``), packages were produced
(``report_production``), something broke (``fault``). Everything runs on the server's event loop:
equipment that works in its own thread must hand its calls over with
``loop.call_soon_threadsafe``.

A hook that refuses (``validate_start``, ``on_unit_mode``, ``on_mach_speed``, ``on_product``,
``on_parameter``, ``on_remote_command``, ``on_interlock``) raises ``uacell.core.errors.CallError``; the
model then changes nothing and the client gets that status code. An acting-state hook that raises
anything else is logged and turned into a fault (the unit aborts).
"""

from __future__ import annotations

from collections.abc import Awaitable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

from uacell.packml.types import (
    PackMLDescriptorDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
)


class UnitPort(Protocol):
    """What the equipment may call on the model."""

    def now(self) -> float:
        """The model's monotonic clock, in seconds."""
        ...

    @property
    def acting_state(self) -> str | None:
        """The acting state that runs (it ends when the equipment completes it), if any."""
        ...

    @property
    def state(self) -> str:
        """The unit's innermost current state (e.g. ``"Execute"``, ``"Stopped"``, ``"Aborted"``)."""
        ...

    @property
    def cur_mach_speed(self) -> float:
        """The speed to produce at now (packages/min): MachSpeed in Execute, else 0."""
        ...

    def state_complete(self, state: str | None = None) -> bool:
        """The acting state ``state`` (default: whichever runs) is done; False if it no longer runs."""
        ...

    def report_production(self, processed: int = 0, defective: int = 0, consumed: int | Mapping[int, int] = 0) -> None:
        """Add to ProdProcessedCount[0] / ProdDefectiveCount[0] / ProdConsumedCount (by ID or [0])."""
        ...

    def fault(self, alarm_id: int, message: str, *, value: int = 0, category: int = 1) -> None:
        """Raise an alarm, record it as StopReason (first out) and abort the unit."""
        ...

    def warning(self, warning_id: int, message: str, *, active: bool = True) -> None:
        """Raise (or, with ``active=False``, clear) a warning; warnings never stop the unit."""
        ...

    def set_blocked(self, blocked: bool) -> None: ...

    def set_starved(self, starved: bool) -> None: ...

    def state_numbered(self, number: int) -> str | None:
        """The TR88 state with StateNumber ``number`` (as the NodeSet numbers them), if any."""
        ...

    def path_to(self, state: str) -> list[tuple[str, str]]:
        """The fewest TR88 steps from the current innermost state to ``state``, each (the method to
        take, or ``"complete"`` for an acting state's end; the state it leads to)."""
        ...

    def equipment_command(self, method: str) -> None:
        """Take a transition the machine itself decides (Hold, Suspend, Unhold, Unsuspend, ToComplete,
        Stop, Abort); the same state rules as for clients apply."""
        ...

    def equipment_unit_mode(self, mode: int) -> bool:
        """The machine changed its unit mode by itself; False (nothing changes) for an unsupported mode."""
        ...

    def equipment_alarms(self, alarms: Mapping[int, str]) -> None:
        """The alarms the machine has active now (ID -> message) become Admin.Alarm."""
        ...

    def equipment_speeds(self, mach_speed: float | None = None, cur_mach_speed: float | None = None) -> None:
        """The machine's own MachSpeed set point and the speed it runs at now (a PLC's
        ``Status.MachSpeed`` / ``Status.CurMachSpeed``): shown as they are. None leaves a value as it is;
        once the machine reported CurMachSpeed, it is no longer derived from MachSpeed and the state."""
        ...

    def equipment_condition(self, name: str, active: bool, message: str) -> None:
        """Raise (``active``) or clear the alarm condition ``name``, one the equipment declares in an
        optional ``condition_names`` attribute (OPC 10000-9 conditions in ``<unit>/Conditions``)."""
        ...


@runtime_checkable
class PackMLEquipment(Protocol):
    """One hook per acting state and per unit command. ``EquipmentBase`` implements all as no-ops."""

    def attach(self, unit: UnitPort) -> None: ...

    def poll(self, now: float) -> None:
        """Called periodically by ``PackMLUnit.tick``; equipment without its own timing uses it."""
        ...

    # Acting states: do the work, then call ``unit.state_complete(<state>)``.
    def on_clearing(self) -> None: ...
    def on_stopping(self) -> None: ...
    def on_aborting(self) -> None: ...
    def on_resetting(self) -> None: ...
    def on_starting(self, parameters: Sequence[PackMLDescriptorDataType]) -> None: ...
    def on_completing(self) -> None: ...
    def on_holding(self) -> None: ...
    def on_unholding(self) -> None: ...
    def on_suspending(self) -> None: ...
    def on_unsuspending(self) -> None: ...

    def on_execute(self) -> None:
        """Execute was entered: produce at ``unit.cur_mach_speed``."""
        ...

    def on_state(self, state: str) -> None:
        """The unit's innermost state changed (called for every state, before the acting hook)."""
        ...

    # Commands that may be refused by raising CallError (nothing has changed yet).
    def validate_start(self, parameters: Sequence[PackMLDescriptorDataType]) -> None: ...
    def on_unit_mode(self, mode: int) -> None: ...
    def on_mach_speed(self, speed: float) -> None: ...
    def on_product(self, products: Sequence[PackMLProductDataType]) -> None: ...
    def on_parameter(self, parameters: Sequence[PackMLDescriptorDataType]) -> None: ...
    def on_remote_command(self, commands: Sequence[PackMLRemoteInterfaceDataType]) -> None: ...
    def on_interlock(self, interlock_id: int, interlocked: bool) -> None: ...

    def close(self) -> Awaitable[None] | None:
        """The server shuts down: release the controller (a coroutine is awaited)."""
        ...


class EquipmentBase:
    """No-op implementation of every hook: subclass it and override what your equipment does.

    With this base alone acting states never complete; call ``self.unit.state_complete()`` when the
    physical action is done.
    """

    unit: UnitPort

    def attach(self, unit: UnitPort) -> None:
        self.unit = unit

    def poll(self, now: float) -> None:
        pass

    def on_clearing(self) -> None:
        pass

    def on_stopping(self) -> None:
        pass

    def on_aborting(self) -> None:
        pass

    def on_resetting(self) -> None:
        pass

    def on_starting(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        pass

    def on_completing(self) -> None:
        pass

    def on_holding(self) -> None:
        pass

    def on_unholding(self) -> None:
        pass

    def on_suspending(self) -> None:
        pass

    def on_unsuspending(self) -> None:
        pass

    def on_execute(self) -> None:
        pass

    def on_state(self, state: str) -> None:
        pass

    def validate_start(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        pass

    def on_unit_mode(self, mode: int) -> None:
        pass

    def on_mach_speed(self, speed: float) -> None:
        pass

    def on_product(self, products: Sequence[PackMLProductDataType]) -> None:
        pass

    def on_parameter(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        pass

    def on_remote_command(self, commands: Sequence[PackMLRemoteInterfaceDataType]) -> None:
        pass

    def on_interlock(self, interlock_id: int, interlocked: bool) -> None:
        pass

    def close(self) -> Awaitable[None] | None:
        return None


class InstantEquipment(EquipmentBase):
    """Completes every acting state at once (useful for tests and dry runs)."""

    def on_state(self, state: str) -> None:
        # The model defers completions requested from inside a hook until the hook returns.
        self.unit.state_complete(state)


# --- optional capabilities: equipment declares them by implementing the Protocol -------------------


@runtime_checkable
class CommandForwarder(Protocol):
    """Equipment whose PLC owns the state (a gateway driver): a unit command or SetUnitMode passes
    uacell's rules, then must be accepted by the PLC before uacell's machines take it
    (docs/equipment.md, "Gateway")."""

    async def send_command(self, machine: str | None, method: str, args: Sequence[Any]) -> None: ...


@runtime_checkable
class NamedConditions(Protocol):
    """Equipment with OPC 10000-9 conditions of its own, in ``<unit>/Conditions``, by name."""

    @property
    def condition_names(self) -> Sequence[str]: ...


@runtime_checkable
class PollHint(Protocol):
    """Equipment that says when it next needs ``poll``: the unit's ticks skip it until then, or until
    its Admin times pass a whole second or a save is due (a waiting simulated unit is ticked about
    three times a second instead of ten). Without it, equipment is polled at every tick."""

    def next_poll(self, now: float) -> float:
        """The unit-clock time of the next ``poll`` this equipment needs (``now``: at once; ``math.inf``:
        none until the unit tells it something, which always ends the skipping)."""
        ...
