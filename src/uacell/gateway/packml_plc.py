"""A PackML unit whose state machine runs in a PLC, followed and commanded over the PLC's PackTags:
the one unit behind both PackTags drivers, ``opcua-packtags`` (``packml_opcua``) and
``modbus-packtags`` (``packml_modbus``); docs/equipment.md, "Gateway". The transport is a
``TagLink``: it reads, writes and watches tags by address and says whether the PLC answers.

The PLC owns the state. A command a client calls is first checked by uacell's own rules (roles,
Executable, locks, the TR88 table), then written as PackTags (Start's parameters to
``Command.Parameter[i].Value``, then ``Command.CntrlCmd``, then ``Command.CmdChangeRequest``); the call
answers Good once the PLC accepted it (its state moved), Bad_InvalidState when the PLC took the
request and did nothing, Bad_Timeout when it did not take it in ``confirm_timeout`` (the request is
cleared again), Bad_CommunicationError without a connection. uacell's three state machines then
follow ``Status.StateCurrent``: an acting state the PLC leaves is completed, a transition the PLC
takes on its own (Complete, Hold, Abort on a fault with ``Admin.StopReason``) is taken as the
machine's own; production counts follow ``Admin.ProdProcessedCount`` / ``ProdDefectiveCount``;
SetMachSpeed writes ``Command.MachSpeed``. While the PLC cannot be reached every command answers
Bad_CommunicationError and is not Executable, and the unit shows warning 9001 ("communication
lost"); it resumes from the PLC's state when the PLC answers again. Nothing is queued or replayed.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.core.errors import CallError
from uacell.gateway.errors import CommunicationError
from uacell.gateway.handshake import Handshake, PlcStatus
from uacell.gateway.link import TagLink
from uacell.gateway.packtags import NEEDED_BY, ResolvedTag
from uacell.packml.equipment import EquipmentBase
from uacell.packml.model import COMPLETE, TR88_COMMANDS
from uacell.packml.types import PackMLDescriptorDataType

log = logging.getLogger(__name__)

UNIT_SETTINGS = ("map", "parameters", "alarms", "confirm_timeout")  # what both PackTags drivers take
COMMUNICATION_WARNING = 9001
COMMUNICATION = "CommunicationLost"  # the unit's alarm condition while the PLC cannot be reached
# uacell's method -> the PackTags command
PACKTAGS_COMMAND = {"ToComplete": "Complete"}
# the tags the unit follows (with Admin.Alarm[i].ID when there are alarms)
WATCHED = (
    "Status.StateCurrent", "Status.UnitModeCurrent", "Status.MachSpeed", "Status.CurMachSpeed",
    "Admin.ProdProcessedCount", "Admin.ProdDefectiveCount", "Admin.StopReason",
)  # fmt: skip
# what a command's handshake reads, in one Read
STATUS = ("Status.StateCurrent", "Command.CmdChangeRequest", "Status.UnitModeCurrent", "Command.UnitModeChangeRequest")
SPEEDS = ("Status.MachSpeed", "Status.CurMachSpeed")  # the PLC's: shown as it reports them


@dataclass(frozen=True)
class Timing:
    confirm_timeout: float = 3.0
    poll: float = 0.01


def timing_of(settings: Mapping[str, Any]) -> Timing:
    return Timing(confirm_timeout=float(settings.get("confirm_timeout", Timing.confirm_timeout)))


class PackTagsUnit(EquipmentBase):
    condition_names = (COMMUNICATION,)

    def __init__(
        self,
        part: str,
        link: TagLink,
        tags: Mapping[str, ResolvedTag],
        timing: Timing,
        release: Callable[[Any], Awaitable[None]],
    ) -> None:
        self.part, self.link, self.tags, self.timing = part, link, dict(tags), timing
        self._release = release
        self.plc: dict[str, Any] = {}  # tag key -> last value
        self._by_address = {t.address: k for k, t in self.tags.items()}
        self.reachable = False
        self._inflight = False
        self._counted: dict[str, int] = {}
        self._attached = False
        self._aborting = False
        self._lost = False  # what the CommunicationLost condition says
        self.missing: dict[str, str] = {}  # tag key -> what the PLC said of it (it has no such tag)
        self._said: set[tuple[str, str]] = set()  # missing tags logged (once each)

    # -- the PLC's values -------------------------------------------------------------------------

    def _tag(self, key: str) -> str:
        return self.tags[key].address

    def on_value(self, address: str, value: Any) -> None:
        key = self._by_address.get(address)
        if key is None:
            return
        expected = self.tags[key].type_name
        if value is not None and not _is(value, expected):
            log.error("%s: %s (%s) holds %r, not a %s", self.part, key, address, value, expected)
            return
        self.plc[key] = value
        if key in ("Admin.ProdProcessedCount", "Admin.ProdDefectiveCount"):
            self._count(key, int(value))
        elif key == "Status.StateCurrent" and not self._inflight:
            self.follow()
        elif key == "Status.UnitModeCurrent" and not self._inflight and self._attached and value:
            self.unit.equipment_unit_mode(int(value))  # a mode the PLC changed by itself
        elif key.startswith("Admin.Alarm[") and self._attached:
            self._alarms()
        elif key in SPEEDS and self._attached:
            self._speeds()

    def _speeds(self) -> None:
        """MachSpeed and CurMachSpeed are the PLC's (the cell file's ``mach_speed`` only stands where the
        PLC has no ``Status.MachSpeed``)."""
        mach, cur = (self.plc.get(k) for k in SPEEDS)
        if mach is not None or cur is not None:
            self.unit.equipment_speeds(
                float(mach) if mach is not None else None, float(cur) if cur is not None else None
            )

    def _alarms(self) -> None:
        """Admin.Alarm follows the PLC's Admin.Alarm[i].ID tags (0: an empty entry)."""
        ids = [int(v) for k, v in self.plc.items() if k.startswith("Admin.Alarm[") and v]
        self.unit.equipment_alarms({i: f"PLC alarm {i}" for i in ids})

    def on_connection(self, connected: bool) -> None:
        self.reachable = connected
        if connected:
            self._take_missing()
        if not self._attached:
            return
        self._tell_lost(not connected)
        if connected:
            self._catch_up()

    def _take_missing(self) -> None:
        """The tags the PLC does not have, as the link found them on connecting: each is one log line
        (once), and the unit works without it; what needs it is refused (``_need``)."""
        found = self.link.missing
        self.missing = {k: found[t.address] for k, t in self.tags.items() if t.address in found}
        for key, reason in self.missing.items():
            self.plc.pop(key, None)
            if (key, reason) not in self._said:
                self._said.add((key, reason))
                needed = [what for what, keys in NEEDED_BY.items() if key in keys]
                effect = f"{', '.join(needed)} refused until it is there" if needed else "the unit works without it"
                log.warning("%s: the PLC has no %s (%s: %s); %s", self.part, key, self._tag(key), reason, effect)

    def _need(self, keys: Sequence[str]) -> None:
        """CallError (Bad_ConfigurationError) naming the first of ``keys`` the PLC does not have."""
        for key in keys:
            if key in self.missing:
                raise CallError(
                    "BadConfigurationError", f"the PLC has no {key} ({self._tag(key)}: {self.missing[key]})"
                )

    def _tell_lost(self, lost: bool) -> None:
        """Warning 9001 in Admin.Warning (PackML's view) and the CommunicationLost condition (alarm
        clients' view) while the PLC cannot be reached."""
        message = f"communication lost: {self.link.endpoint}"
        self.unit.warning(COMMUNICATION_WARNING, message, active=lost)
        if self._lost != lost:
            self._lost = lost
            self.unit.equipment_condition(COMMUNICATION, lost, message if lost else f"{self.link.endpoint} answers")

    def _count(self, key: str, value: int) -> None:
        before = self._counted.get(key)
        self._counted[key] = value
        if before is None or value <= before or not self._attached:
            return  # the first value is where the PLC's count stands; a reset of the PLC's count is not production
        delta = value - before
        if key == "Admin.ProdProcessedCount":
            self.unit.report_production(processed=delta)
        else:
            self.unit.report_production(defective=delta)

    # -- the model follows the PLC ----------------------------------------------------------------

    def attach(self, unit: Any) -> None:
        super().attach(unit)
        self._attached = True
        if not self.reachable:
            self._tell_lost(True)
        asyncio.get_running_loop().call_soon(self._catch_up)

    def _catch_up(self) -> None:
        """What the PLC holds now, taken over: its state, its unit mode, its alarms."""
        mode = self.plc.get("Status.UnitModeCurrent")
        if mode and not self._inflight:
            self.unit.equipment_unit_mode(int(mode))
        if any(k.startswith("Admin.Alarm[") for k in self.tags):
            self._alarms()
        self._speeds()
        self.follow()

    def follow(self) -> None:
        """Bring uacell's machines to the PLC's state by the fewest TR88 steps (the model's ``path_to``,
        from the NodeSet's transitions): an acting state the PLC left is completed, a command it took
        is taken; an abort is recorded with the PLC's StopReason."""
        if not self._attached or self._inflight:
            return
        target = self.unit.state_numbered(int(self.plc.get("Status.StateCurrent", 0) or 0))
        if target is None:
            return
        for _ in range(12):
            current = self.unit.state
            steps = self.unit.path_to(target)
            if not steps:
                break
            action, _next = steps[0]
            try:
                if action == COMPLETE:
                    self.unit.state_complete(current)
                elif action == "Abort":  # the PLC aborted: with its StopReason, read now (it may come after the state)
                    if not self._aborting:
                        self._aborting = True
                        asyncio.get_running_loop().create_task(self._abort_with_reason())
                    return
                else:
                    self.unit.equipment_command(action)
            except CallError:
                break
        if self.unit.state != target:
            log.warning(
                "%s: the PLC is in %s, uacell's machines in %s (no TR88 step leads there)",
                self.part,
                target,
                self.unit.state,
            )

    async def _abort_with_reason(self) -> None:
        try:
            missing = "Admin.StopReason" in self.missing
            reason = 0 if missing else int(await self.link.read(self._tag("Admin.StopReason")) or 0)
        except CommunicationError:
            reason = 0
        finally:
            self._aborting = False
        if self.unit.state in ("Aborting", "Aborted"):
            self.follow()
            return
        try:
            if reason:
                self.unit.fault(reason, f"the PLC stopped the unit (StopReason {reason})")
            else:
                self.unit.equipment_command("Abort")
        except CallError:
            pass
        self.follow()

    # -- commands ---------------------------------------------------------------------------------

    async def send_command(self, machine: str | None, method: str, args: Sequence[Any]) -> None:
        """Write a machine command as PackTags and wait until the PLC accepted it (module doc)."""
        if machine is None and method == "SetUnitMode":
            self._need(NEEDED_BY["SetUnitMode"])
            await self._handshake(
                method, lambda st, now: Handshake.unit_mode(int(args[0]), st, now, self.timing.confirm_timeout)
            )
            return
        if machine is None:
            return  # SetMachSpeed writes Command.MachSpeed (on_mach_speed); the other unit methods stay uacell's
        name = PACKTAGS_COMMAND.get(method, method)
        if name not in TR88_COMMANDS:
            return
        self._need(NEEDED_BY["every command"])
        parameters: list[float] = []
        if method == "Start" and args:
            given: Sequence[PackMLDescriptorDataType] = args[0] or ()
            parameters = [float(p.value) for p in given]
            room = self._parameter_room()
            if len(parameters) > room:
                raise CallError(
                    "BadInvalidArgument", f"the PLC takes {room} parameters, not {len(parameters)}", argument=0
                )
        if method == "Start":  # every slot written: the slots Start does not use hold 0.0, not an older value
            parameters += [0.0] * (self._parameter_room() - len(parameters))
        await self._handshake(
            method, lambda st, now: Handshake.command(name, st, now, self.timing.confirm_timeout, parameters)
        )

    def _parameter_room(self) -> int:
        """How many ``Command.Parameter[i].Value`` slots the PLC has, from 0 on without a gap."""
        room = 0
        while (
            f"Command.Parameter[{room}].Value" in self.tags and f"Command.Parameter[{room}].Value" not in self.missing
        ):
            room += 1
        return room

    async def _handshake(self, method: str, make: Any) -> None:
        """Write the handshake ``make(status, now)`` builds and wait until the PLC accepted it."""
        self._inflight = True
        try:
            status = await self._status()
            try:
                shake: Handshake = make(status, time.monotonic())
            except CallError as e:
                log.info("%s: %s not sent to the PLC: %s (%s)", self.part, method, e.message, e.status)
                raise
            try:
                # one Write request: the PLC sees the parameters, the command and its request together
                await self.link.write_many(
                    [(self._tag(w.tag), w.value, self.tags[w.tag].type_name) for w in shake.writes]
                )
                while not shake.observe(await self._status(), time.monotonic()):
                    await asyncio.sleep(self.timing.poll)
            except CallError as e:
                log.info("%s: %s was not accepted by the PLC: %s (%s)", self.part, method, e.message, e.status)
                if e.status != "BadCommunicationError":
                    for w in shake.undo:
                        await self.link.write(self._tag(w.tag), w.value, "Boolean")
                raise
        except CommunicationError as e:
            raise CallError("BadCommunicationError", str(e)) from None
        finally:
            self._inflight = False
            asyncio.get_running_loop().call_soon(self.follow)  # after the model took the command

    async def _status(self) -> PlcStatus:
        keys = [k for k in STATUS if k not in self.missing]
        try:  # in one Read: a cleared request and the state it led to come from the same scan
            got = dict(zip(keys, await self.link.read_many([self._tag(k) for k in keys]), strict=True))
        except CommunicationError:
            return PlcStatus(0, 0, False, connected=False)
        state, request, mode, mode_request = (got.get(k) for k in STATUS)
        self.plc["Status.StateCurrent"] = state
        return PlcStatus(int(state or 0), int(mode or 0), bool(request), bool(mode_request))

    def on_mach_speed(self, speed: float) -> None:
        if not self.reachable:
            raise CallError("BadCommunicationError", f"no connection to the PLC at {self.link.endpoint}")
        self._need(NEEDED_BY["SetMachSpeed"])
        task = asyncio.get_running_loop().create_task(self._set_speed(float(speed)))
        task.add_done_callback(_log_failure(self.part, "Command.MachSpeed"))

    async def _set_speed(self, speed: float) -> None:
        """SetMachSpeed does not wait for the PLC: the model shows the request at once; this writes it,
        then shows what the PLC's ``Status.MachSpeed`` says once it took it (or ``confirm_timeout``
        passed: a PLC that keeps its own set point is shown with it)."""
        await self.link.write(self._tag("Command.MachSpeed"), speed, "Float")
        if "Status.MachSpeed" not in self.tags or "Status.MachSpeed" in self.missing:
            return
        deadline = time.monotonic() + self.timing.confirm_timeout
        while True:
            reported = await self.link.read(self._tag("Status.MachSpeed"))
            took = _is(reported, "Float") and abs(reported - speed) <= 1e-4 * max(1.0, abs(speed))
            if took or time.monotonic() >= deadline:
                break
            await asyncio.sleep(self.timing.poll * 5)
        if _is(reported, "Float"):
            self.plc["Status.MachSpeed"] = reported
            self._speeds()

    def close(self) -> Awaitable[None]:
        return self._release(self.link)


def _log_failure(part: str, what: str) -> Any:
    def done(task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            log.warning("%s: writing %s failed: %s", part, what, task.exception())

    return done


def _is(value: Any, type_name: str) -> bool:
    if type_name == "Boolean":
        return isinstance(value, bool)
    if type_name == "Int32":
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, float | int) and not isinstance(value, bool)


async def start_unit(
    part: str, link: TagLink, tags: Mapping[str, ResolvedTag], settings: Mapping[str, Any], release: Any
) -> PackTagsUnit:
    """The unit on ``link``, its tags watched; it waits up to 3 s for the PLC (unreachable at start:
    uacell serves anyway, the unit reports it)."""
    unit = PackTagsUnit(part, link, tags, timing_of(settings), release)
    watched = [tags[k].address for k in WATCHED] + [t.address for k, t in tags.items() if k.startswith("Admin.Alarm[")]
    # the tags uacell only writes are tried too, once a connection: a tag the PLC does not have is found then
    checked = [t.address for t in tags.values() if t.address not in watched]
    labels = {t.address: f"{part}: {k}" for k, t in tags.items()}
    link.start()
    await link.watch(watched, unit.on_value, unit.on_connection, labels, checked)
    await link.wait_connected(3.0)
    return unit
