"""Alarm conditions as the models keep them (OPC 10000-9 AlarmConditionType: active, acknowledged,
enabled, a comment), pure. A part's equipment names its conditions and raises or clears them; clients
acknowledge, comment, enable and disable them through the binding (``uacell.binding.conditions``).

A robot controller's conditions live in SystemOperation/Conditions (decision 18); a PackML unit
behind a PLC has ``CommunicationLost`` under ``<unit>/Conditions`` (decision 45).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from uacell.core.errors import CallError

log = logging.getLogger(__name__)


@dataclass
class Condition:
    """One acknowledgeable alarm condition."""

    name: str
    message: str = ""
    active: bool = False
    acked: bool = True
    enabled: bool = True  # OPC 10000-9 Enable/Disable: a disabled condition is not reported nor evaluated
    comment: str = ""


class ConditionSet:
    """A part's conditions by name; ``condition_listeners`` hear of every change (with the condition)."""

    def __init__(self, names: Iterable[str] = ()) -> None:
        self.conditions: dict[str, Condition] = {n: Condition(n) for n in names}
        self.condition_listeners: list[Callable[[Condition], None]] = []

    def conditions_changed(self) -> None:
        """Called after every change, once the listeners heard of it (a model's hook)."""

    def alarm(self, name: str, active: bool, message: str) -> None:
        """The equipment raises (``active``) or clears the condition ``name``; raising it wants an
        acknowledgement again."""
        cond = self.conditions.setdefault(name, Condition(name))
        cond.message = message
        cond.active = active
        if active:
            cond.acked = False
        log.info("condition %s %s: %s", name, "active" if active else "inactive", message)
        self._condition_changed(cond)

    def acknowledge(self, name: str, comment: str = "") -> None:
        """The condition's Acknowledge method."""
        cond = self._condition(name)
        if not cond.enabled:
            raise CallError("BadConditionDisabled", f"{name} is disabled")
        if cond.acked:
            raise CallError("BadConditionBranchAlreadyAcked", f"{name} is already acknowledged")
        cond.acked = True
        if comment:
            cond.comment = comment
        log.info("condition %s acknowledged%s", name, f": {comment}" if comment else "")
        self._condition_changed(cond)

    def add_comment(self, name: str, comment: str) -> None:
        """The condition's AddComment method (OPC 10000-9, 5.5.5)."""
        cond = self._condition(name)
        if not cond.enabled:
            raise CallError("BadConditionDisabled", f"{name} is disabled")
        cond.comment = comment
        log.info("condition %s comment: %s", name, comment)
        self._condition_changed(cond)

    def set_enabled(self, name: str, enabled: bool) -> None:
        """The condition's Enable / Disable methods (OPC 10000-9, 5.5.4)."""
        cond = self._condition(name)
        if cond.enabled == enabled:
            status = "BadConditionAlreadyEnabled" if enabled else "BadConditionAlreadyDisabled"
            raise CallError(status, f"{name} is already {'enabled' if enabled else 'disabled'}")
        cond.enabled = enabled
        log.info("condition %s %s", name, "enabled" if enabled else "disabled")
        self._condition_changed(cond)

    def _condition(self, name: str) -> Condition:
        cond = self.conditions.get(name)
        if cond is None:
            raise CallError("BadNodeIdUnknown", f"no condition {name!r}")
        return cond

    def _condition_changed(self, cond: Condition) -> None:
        for listener in list(self.condition_listeners):
            listener(cond)
        self.conditions_changed()
