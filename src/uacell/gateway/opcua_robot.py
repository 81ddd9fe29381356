"""A robot whose remote-operation signals live in a PLC's OPC UA server: the ``opcua-signals`` driver
(docs/equipment.md, "Robots over OPC UA signals").

    [[robots.controllers]]
    name = "Cabinet"
    equipment = { driver = "opcua-signals", endpoint = "opc.tcp://10.0.0.5:4840/", prefix = "ns=3;s=Robot1" }
    programs = { pick_and_place = 3, palletize = 7 }

The signal set, the handshakes and every rule are those of ``modbus-signals`` (the same
``ModbusSignalsRobot`` runs them); only the transport differs: each signal is a variable of the PLC,
``<prefix>.<signal>`` (a string NodeId prefix) or ``<prefix>/<ns>:<signal>`` (a browse path prefix),
or its own ``map`` entry; the watched ones are subscribed through the PLC's shared link
(``opcua_link``: security, user, subscribe or poll), the status is their latest values.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.core.errors import CallError
from uacell.gateway import DriverSettings
from uacell.gateway.errors import CommunicationError
from uacell.gateway.handshake import Write
from uacell.gateway.opcua_link import LINK_SETTINGS, PlcLink, link_options, link_pool, shared_link
from uacell.gateway.signal_robot import ModbusSignalsRobot, Timing, check_programs, perform
from uacell.gateway.signals import (
    DEFAULT_MAP,
    NAME_SIGNALS,
    SAFETY_SIGNALS,
    STATUS_SIGNALS,
    UNITS,
    RobotStatus,
    SignalOp,
)
from uacell.robotics.sim import DEFAULT_AXES

SETTINGS = (
    *LINK_SETTINGS, "prefix", "map", "types", "programs", "confirm_timeout", "pulse_width", "pulse_gap", "motion",
)  # fmt: skip
POOL = link_pool()
# the built-in types uacell writes the signals as (``types`` changes them, e.g. program_number = "UInt16")
WRITE_TYPES = {"program_number": "Int32", "program_name": "String"}
MOTION_KEYS = ("position", "speed", "scale", "speed_scale", "unit")
_BLANK = RobotStatus()
CONNECT_WAIT = 3.0  # seconds start-up waits for the PLC (then uacell serves anyway: it reports the loss)


@dataclass(frozen=True)
class MotionTags:
    """The axes' variables: one address per axis, or one address holding an array of all axes."""

    position: tuple[str, ...]
    speed: tuple[str, ...] = ()
    scale: float = 1.0
    speed_scale: float = 1.0
    unit: str = "deg"


def signal_address(prefix: str, signal: str) -> str:
    """``<prefix>.<signal>`` for a NodeId prefix, ``<prefix>/<ns>:<signal>`` for a browse path."""
    if prefix.startswith("/"):
        last = prefix.rsplit("/", 1)[-1]
        ns = last.split(":", 1)[0] if ":" in last else "0"
        return f"{prefix}/{ns}:{signal}"
    return f"{prefix}.{signal}"


def parse_motion_tags(table: Mapping[str, Any]) -> MotionTags:
    unknown = sorted(set(table) - set(MOTION_KEYS))
    if unknown:
        raise ValueError(f"motion has no key {unknown[0]!r} (it knows {', '.join(MOTION_KEYS)})")

    def addresses(key: str) -> tuple[str, ...]:
        value = table.get(key, ())
        return (value,) if isinstance(value, str) else tuple(str(v) for v in value)

    unit = str(table.get("unit", "deg"))
    if unit not in UNITS:
        raise ValueError(f"motion unit {unit!r} is not one of {', '.join(UNITS)}")
    if not addresses("position"):
        raise ValueError("motion needs position: one address per axis, or one holding an array")
    return MotionTags(
        addresses("position"), addresses("speed"), float(table.get("scale", 1.0)),
        float(table.get("speed_scale", 1.0)), unit,
    )  # fmt: skip


class OpcuaRobotIO:
    """The signal operations over a PLC link: the status from the watched values, writes in one
    Write request per operation step. A lost link: ``connected=False``, writes Bad_CommunicationError."""

    def __init__(
        self,
        link: PlcLink,
        addresses: Mapping[str, str],
        *,
        by_name: bool = False,
        safety: Sequence[str] = (),
        motion: MotionTags | None = None,
        axes: int = 0,
        types: Mapping[str, str] | None = None,
        poll: float = 0.01,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.link, self.addresses, self.poll, self.clock = link, dict(addresses), poll, clock
        self.signals = (*STATUS_SIGNALS, *(("program_name_echo",) if by_name else ()), *safety)
        self.motion, self.axes = motion, axes
        self.types = {**WRITE_TYPES, **(types or {})}
        self._values: dict[str, Any] = {}
        self._watched = {self.addresses[s]: s for s in self.signals}
        if motion is not None:
            for kind, group in (("position", motion.position), ("speed", motion.speed)):
                for i, address in enumerate(group):
                    self._watched[address] = f"axis{i + 1}.{kind}"
        self._connected = False

    @property
    def name(self) -> str:
        return self.link.endpoint

    async def start(self) -> None:
        labels = {a: s for a, s in self._watched.items()}
        await self.link.watch(list(self._watched), self._value, self._state, labels)
        self.link.start()

    def _value(self, address: str, value: Any) -> None:
        self._values[self._watched[address]] = value

    def _state(self, connected: bool) -> None:
        self._connected = connected

    def _axes(self, kind: str, group: tuple[str, ...], scale: float) -> tuple[float, ...]:
        to_deg = UNITS[self.motion.unit] if self.motion else 1.0
        if len(group) == 1 and self.axes > 1:  # one array for all axes
            values = list(self._values.get(f"axis1.{kind}") or [])
        else:
            values = [self._values.get(f"axis{i + 1}.{kind}") for i in range(len(group))]
        out = [float(v) * scale * to_deg if isinstance(v, int | float) else math.nan for v in values[: self.axes]]
        return tuple(0.0 if math.isnan(v) else v for v in out)

    async def status(self) -> RobotStatus:
        """The latest values (no request); ``connected=False`` while the link is down or a value is missing."""
        if not self._connected or any(s not in self._values for s in self.signals):
            return RobotStatus(connected=False)
        fields: dict[str, Any] = {}
        for signal in self.signals:  # as RobotStatus holds it: bool, int or str
            kind = type(getattr(_BLANK, signal))
            value = self._values[signal]
            fields[signal] = kind(value) if value is not None else kind()
        if self.motion is not None:
            fields["positions"] = self._axes("position", self.motion.position, self.motion.scale)
            if self.motion.speed:
                fields["speeds"] = self._axes("speed", self.motion.speed, self.motion.speed_scale)
        return RobotStatus(**fields)

    def _type(self, signal: str) -> str:
        return self.types.get(signal, "Boolean")

    async def _write(self, writes: tuple[Write, ...]) -> None:
        if writes:
            await self.link.write_many([(self.addresses[w.tag], w.value, self._type(w.tag)) for w in writes])

    async def write_signal(self, signal: str, value: bool | int | str) -> None:
        try:
            await self._write((Write(signal, value),))
        except CommunicationError as exc:
            raise CallError("BadCommunicationError", f"{signal}: {exc}") from None

    async def perform(self, op: SignalOp) -> None:
        """Write ``op``, wait for its confirmation in the subscribed values."""
        await perform(op, self._write, self.status, self.poll, self.clock)

    async def close(self) -> None:
        await POOL.release(self.link)


def signal_addresses(prefix: str, overrides: Mapping[str, str]) -> dict[str, str]:
    """Every signal's address: its ``map`` entry, else below ``prefix``; unknown signals refused."""
    for name in overrides:
        if name not in DEFAULT_MAP:
            raise ValueError(f"{name}: not a signal of the map ({', '.join(DEFAULT_MAP)})")
    missing = [s for s in DEFAULT_MAP if s not in overrides and s not in SAFETY_SIGNALS]
    if missing and not prefix:
        raise ValueError(f"prefix is needed for the signals map does not give ({', '.join(missing)})")
    return {s: str(overrides.get(s) or signal_address(prefix, s)) for s in DEFAULT_MAP}


def robot_addresses(settings: Mapping[str, Any]) -> dict[str, str]:
    """Every variable the driver reads or writes, by signal (and ``axisN.position``/``speed``): the
    name signals only when a program is selected by name, the safety signals only when mapped."""
    overrides = {str(k): str(v) for k, v in dict(settings.get("map", {})).items()}
    addresses = signal_addresses(str(settings.get("prefix", "")), overrides)
    by_name = any(isinstance(v, str) for v in dict(settings.get("programs", {})).values())
    used = {
        k: a for k, a in addresses.items()
        if (by_name or k not in NAME_SIGNALS) and (k in overrides or k not in SAFETY_SIGNALS)
    }  # fmt: skip
    if "motion" in settings:
        motion = parse_motion_tags(settings["motion"])
        for kind, group in (("position", motion.position), ("speed", motion.speed)):
            used.update({f"axis{i + 1}.{kind}": a for i, a in enumerate(group)})
    return used


async def opcua_signals(spec: Any) -> ModbusSignalsRobot:
    """The equipment factory of the ``opcua-signals`` driver (``spec``: a ControllerEquipmentSpec)."""
    settings = DriverSettings("opcua-signals", spec.part, spec.settings, SETTINGS)
    options = link_options(spec.part, settings.raw)
    overrides = {str(k): str(v) for k, v in dict(settings.get("map", {})).items()}
    addresses = signal_addresses(str(settings.get("prefix", "")), overrides)
    programs = check_programs(settings.get("programs", {}))
    motion = parse_motion_tags(settings.get("motion")) if "motion" in settings else None
    axes = tuple(getattr(spec, "axes", ())) or DEFAULT_AXES
    timing = Timing(poll=options.interval, **settings.reals(Timing, "confirm_timeout", "pulse_width", "pulse_gap"))
    io = OpcuaRobotIO(
        shared_link(POOL, options, spec.part), addresses,
        by_name=any(isinstance(v, str) for v in programs.values()),
        safety=tuple(k for k in SAFETY_SIGNALS if k in overrides),
        motion=motion, axes=len(axes), types={str(k): str(v) for k, v in dict(settings.get("types", {})).items()},
        poll=min(options.interval, 0.01),
    )  # fmt: skip
    await io.start()
    await io.link.wait_connected(CONNECT_WAIT)  # the first values, when the PLC answers at once
    robot = ModbusSignalsRobot(spec.part, io, None, programs, axes, timing)
    await robot.start()
    return robot
