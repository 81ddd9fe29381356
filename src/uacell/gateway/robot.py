"""A robot behind a remote-operation signal interface on Modbus/TCP, as a ``RobotEquipment``: the
``modbus-signals`` driver (docs/equipment.md, "Gateway").

    [[robots.controllers]]
    name = "Cabinet"
    equipment = { driver = "modbus-signals", host = "10.0.0.7", port = 502, unit = 1 }
    programs = { pick_and_place = 3, palletize = 7 }

The Robotics model keeps every rule (states, roles, locks, Status values); this driver only turns
its requests into the signal handshakes of ``uacell.gateway.signals`` and reports what the
controller does:

- GetReady / StandDown: the ``drives_on`` output, confirmed by ``drives_are_on``;
- LoadByName / LoadByNodeId of a program: its number from ``programs`` (by the name LoadByName
  takes, ``pick_and_place``, or the program's own, ``PickAndPlace``), written with a strobe and
  confirmed by the echo; modules need no selection on such a controller and load as a no-op;
- Start: a pulse, confirmed by ``running``; the run ends when ``running`` falls: completed when
  ``program_end`` is set, stopped otherwise, an ``AlarmStop`` when ``fault`` rose;
- Stop: a pulse, confirmed by ``running`` falling;
- the controller's ``fault`` bit (with ``fault_code``) is the condition ``ControllerFault``, a lost
  connection the condition ``CommunicationLost``; while it is lost ``reachable`` is false and every
  method answers Bad_CommunicationError (Executable false). A poll reconnects, backing off to 2 s.

A handshake the controller does not confirm in ``confirm_timeout`` answers Bad_Timeout, one it
refuses (a fault) Bad_InvalidState; nothing is queued or replayed. Axis positions are not part of
the signals: the axes read 0.
"""

from __future__ import annotations

from typing import Any

from uacell.gateway import DriverSettings
from uacell.gateway.modbus import SHARED
from uacell.gateway.modbus_robot import ModbusRobotIO, parse_motion, signal_tags
from uacell.gateway.signal_robot import ModbusSignalsRobot, Timing, check_programs, program_key
from uacell.gateway.signals import SAFETY_SIGNALS
from uacell.robotics.sim import DEFAULT_AXES

__all__ = ["ModbusSignalsRobot", "Timing", "check_programs", "modbus_signals", "program_key"]

SETTINGS = (
    "host", "port", "unit", "timeout", "poll", "confirm_timeout", "pulse_width", "pulse_gap", "programs", "map",
    "motion",
)  # fmt: skip
POOL = SHARED  # connections shared by every part of the process, per host and port


async def modbus_signals(spec: Any) -> ModbusSignalsRobot:
    """The equipment factory of the ``modbus-signals`` driver (``spec``: a ControllerEquipmentSpec)."""
    settings = DriverSettings("modbus-signals", spec.part, spec.settings, SETTINGS)
    host = settings.host("the controller or PLC")
    port, unit = int(settings.get("port", 502)), int(settings.get("unit", 1))
    programs = check_programs(settings.get("programs", {}))
    overrides = {k: (str(v[0]), int(v[1]), str(v[2])) for k, v in dict(settings.get("map", {})).items()}
    tags = signal_tags(overrides)
    motion = parse_motion(settings.get("motion")) if "motion" in settings else None
    axes = tuple(getattr(spec, "axes", ())) or DEFAULT_AXES
    timing = Timing(**settings.reals(Timing, "poll", "confirm_timeout", "pulse_width", "pulse_gap"))
    conn = POOL.connection(host, port, settings.real("timeout", 1.0), spec.part)
    by_name = any(isinstance(v, str) for v in programs.values())
    safety = tuple(k for k in SAFETY_SIGNALS if k in overrides)
    io = ModbusRobotIO(
        conn, unit, tags, poll=min(timing.poll, 0.01), by_name=by_name, safety=safety, motion=motion, axes=len(axes)
    )
    robot = ModbusSignalsRobot(spec.part, io, conn, programs, axes, timing)
    await robot.start()  # unreachable at start: uacell serves anyway, the part reports it
    return robot
