"""The controller's motion device: axis values sampled while they change, InControl and OnPath."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging

from asyncua import ua

from uacell.core.background import Background
from uacell.core.capabilities import has
from uacell.core.capabilities import reachable as is_reachable
from uacell.robotics.binding.shared import ControllerBinding
from uacell.robotics.equipment import AxisFeed
from uacell.robotics.model import EXECUTING, READY

log = logging.getLogger(__name__)

AXIS_PERIOD = 0.1  # seconds between axis samples
_ROTARY = 1  # AxisMotionProfileEnumeration ROTARY
_AXIS_VALUES = ("ActualPosition", "ActualSpeed", "ActualAcceleration")


class Arm:
    """The motion device of one controller (if it has one)."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding
        self.axis_nodes: list[dict[str, ua.NodeId]] = []
        self._last_axes: list[tuple[float, float]] | None = None
        self._reachable = True  # what the axis values last said about the equipment
        self._background = Background()
        self._fed = False  # the equipment says when its axes change (AxisFeed)
        self._feed_pending = False
        self._fed_at = 0.0

    async def setup(self) -> None:
        b = self.binding
        if b.arm is None:
            return
        # The axes as configured (their BrowseNames), in the order the equipment reports them.
        names = [c.name for c in b.arm.part.children if c.folder == "Axes"]
        for name, _ in zip(names, b.cell.equipment.axes, strict=False):
            axis = b.child(b.arm.node, f"Axes/{name}")
            nodes = {}
            for key in _AXIS_VALUES:
                with contextlib.suppress(KeyError):
                    nodes[key] = b.child(axis, f"ParameterSet/{key}")
            self.axis_nodes.append(nodes)
            with contextlib.suppress(KeyError):
                await b.values.write(b.child(axis, "MotionProfile"), _ROTARY, ua.VariantType.Int32)
        with contextlib.suppress(KeyError):
            await b.values.write(b.child(b.arm.node, "ParameterSet/SpeedOverride"), 100.0, ua.VariantType.Double)
        await self.publish_axes(0.0)
        equipment = b.cell.equipment
        if has(equipment, AxisFeed):
            self._fed = True
            self._fed_at = asyncio.get_running_loop().time()
            equipment.add_axis_listener(self._axes_changed)
        self._background.spawn(self._sample_axes(), name=f"axes-{b.arm.path}")

    def _axes_changed(self) -> None:
        """AxisFeed: the controller's axes were read and changed: published once the publisher runs
        (one pending publication at a time, reading the latest values)."""
        if not self._feed_pending and self._reachable:
            self._feed_pending = True
            self.binding.app.publisher.submit(self._publish_fed)

    async def _publish_fed(self) -> None:
        self._feed_pending = False
        now = asyncio.get_running_loop().time()
        dt, self._fed_at = now - self._fed_at, now
        await self.publish_axes(dt)

    async def _sample_axes(self) -> None:
        loop = asyncio.get_running_loop()
        last = loop.time()
        equipment = self.binding.cell.equipment
        while True:
            await asyncio.sleep(AXIS_PERIOD)
            now = loop.time()
            dt, last = now - last, now
            # a gateway's controller may be away
            reachable = is_reachable(equipment)
            if reachable != self._reachable:
                self._reachable = reachable
                self._last_axes = None  # written afresh once it is back
                if not reachable:
                    self.binding.app.publisher.submit(self._unreachable)
                    continue
            if not reachable or self._fed:
                if reachable and self._last_axes is None:  # back after a loss: written afresh
                    self.binding.app.publisher.submit(functools.partial(self.publish_axes, dt))
                continue
            try:
                states = [(round(a.position, 4), round(a.speed, 4)) for a in equipment.axis_states()]
            except Exception:
                log.exception("reading the axes failed")
                continue
            if states != self._last_axes:
                self.binding.app.publisher.submit(functools.partial(self.publish_axes, dt))

    async def _unreachable(self) -> None:
        """The axis values while the controller cannot be reached: Bad_NoCommunication (not its last values)."""
        bad = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
        for nodes in self.axis_nodes:
            for node in nodes.values():
                await self.binding.values.write_status(node, bad)

    async def publish_axes(self, dt: float) -> None:
        b = self.binding
        equipment = b.cell.equipment
        states = [(round(a.position, 4), round(a.speed, 4)) for a in equipment.axis_states()]
        previous = self._last_axes
        self._last_axes = states
        scale = getattr(equipment, "time_scale", 1.0)
        for i, (nodes, (pos, speed)) in enumerate(zip(self.axis_nodes, states, strict=False)):
            if "ActualPosition" in nodes:
                await b.values.write(nodes["ActualPosition"], pos, ua.VariantType.Double)
            if "ActualSpeed" in nodes:
                await b.values.write(nodes["ActualSpeed"], speed, ua.VariantType.Double)
            if "ActualAcceleration" in nodes:
                accel = 0.0
                if previous is not None and dt > 0:
                    # Speeds are per simulated second; dt is real time.
                    accel = round((speed - previous[i][1]) / (dt / scale), 2)
                await b.values.write(nodes["ActualAcceleration"], accel, ua.VariantType.Double)

    async def publish(self) -> None:
        b = self.binding
        if b.arm is None:
            return
        in_control = b.cell.system.state in (READY, EXECUTING)
        for path in ("ParameterSet/InControl", "ParameterSet/OnPath"):
            with contextlib.suppress(KeyError):
                await b.values.write(b.child(b.arm.node, path), in_control, ua.VariantType.Boolean)

    async def close(self) -> None:
        await self._background.close()
