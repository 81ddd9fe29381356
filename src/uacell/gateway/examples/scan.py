"""The TR88 scan-cycle program of the example PLCs that keep their tags in memory they own (the S7
and the Logix example): each scan takes a change request (clears it; acts on it when TR88 allows
the command in the state), ends an acting state after ``acting`` seconds, produces at MachSpeed
packages/min in Execute. A PLC says how its tags are read and written (``Memory``); the tag names
are the PackTags map's keys (``Admin.StopReason`` for its ID)."""

from __future__ import annotations

import time
from typing import Any, Protocol

from uacell.gateway.examples.packtags_plc import ABORTABLE, ACTING_NEXT, COMMANDS, MODE_CHANGE_IN, S


class Memory(Protocol):
    def get(self, tag: str) -> Any: ...

    def set(self, tag: str, value: Any) -> None: ...

    def switches(self) -> tuple[bool, bool, bool]:
        """The test switches: refuse (requests are taken and ignored), frozen (no scan), fault."""
        ...

    def take_parameters(self) -> None:
        """Keep the Command.Parameter values a Start took where the tests read them."""
        ...


class ScanProgram:
    def __init__(self, memory: Memory, acting: float) -> None:
        self.m, self.acting = memory, acting
        self.entered = time.monotonic()
        self.produced = 0.0
        self.last_scan = time.monotonic()
        self.last_fault = False

    def initialise(self) -> None:
        for tag, value in (
            ("Status.StateCurrent", S["Stopped"]), ("Status.UnitModeCurrent", 1), ("Command.UnitMode", 1),
            ("Command.MachSpeed", 60.0), ("Status.MachSpeed", 60.0),
        ):  # fmt: skip
            self.m.set(tag, value)

    def enter(self, state: int, now: float) -> None:
        self.m.set("Status.StateCurrent", state)
        self.entered = now

    def scan(self, now: float) -> None:
        m = self.m
        refuse, frozen, fault = m.switches()
        if frozen:
            return
        state = int(m.get("Status.StateCurrent"))
        if fault and not self.last_fault and state in ABORTABLE:
            m.set("Admin.StopReason", 42)
            self.enter(state := S["Aborting"], now)
        self.last_fault = fault
        if m.get("Command.CmdChangeRequest"):
            m.set("Command.CmdChangeRequest", False)
            rule = COMMANDS.get(int(m.get("Command.CntrlCmd")))
            if not refuse and rule is not None and state in rule[0]:
                if rule[1] == S["Starting"]:
                    m.take_parameters()
                self.enter(state := rule[1], now)
        if m.get("Command.UnitModeChangeRequest"):
            m.set("Command.UnitModeChangeRequest", False)
            if not refuse and state in MODE_CHANGE_IN:
                m.set("Status.UnitModeCurrent", m.get("Command.UnitMode"))
        speed = float(m.get("Command.MachSpeed"))
        if speed > 0:
            m.set("Status.MachSpeed", speed)
        if state in ACTING_NEXT and now - self.entered >= self.acting:
            self.enter(state := ACTING_NEXT[state], now)
        if state == S["Execute"]:
            m.set("Status.CurMachSpeed", speed)
            self.produced += speed / 60.0 * (now - self.last_scan)
            whole = int(self.produced)
            if whole:
                self.produced -= whole
                m.set("Admin.ProdProcessedCount", int(m.get("Admin.ProdProcessedCount")) + whole)
        else:
            m.set("Status.CurMachSpeed", 0.0)
        self.last_scan = now
