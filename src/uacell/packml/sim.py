"""A simulated packaging unit behind the PackML equipment protocol.

Acting states last a configurable time; in Execute it produces at CurMachSpeed (packages/min), a
configurable share of them defective, consuming material per package. ``inject_fault`` raises an
alarm and aborts the unit. Time comes from the unit's clock through ``poll`` (driven by
``PackMLUnit.tick``), so tests can run it on a fake clock.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

from uacell.packml.equipment import EquipmentBase
from uacell.packml.types import PackMLDescriptorDataType

log = logging.getLogger(__name__)


class SimulatedUnit(EquipmentBase):
    def __init__(
        self,
        acting_time: float = 0.5,
        *,
        acting_times: Mapping[str, float] | None = None,
        defect_share: float = 0.02,
        consumed_per_package: float = 1.0,
        job_size: int | None = None,
    ) -> None:
        if not 0.0 <= defect_share <= 1.0:
            raise ValueError("defect_share must be between 0 and 1")
        self.acting_time = acting_time
        self.acting_times = dict(acting_times or {})
        self.defect_share = defect_share
        self.consumed_per_package = consumed_per_package
        self.job_size = job_size  # packages after which the sim completes the job itself (TR88 SC)
        self.start_parameters: tuple[PackMLDescriptorDataType, ...] = ()
        self.produced_in_job = 0
        self.fault_active: tuple[int, str] | None = None
        self._due: tuple[str, float] | None = None
        self._executing = False
        self._last_poll: float | None = None
        self._made = self._defective = self._consumed = 0.0

    def on_state(self, state: str) -> None:
        # Every acting state simply takes its time; wait states cancel a completion still due.
        if self.unit.acting_state == state:
            self._due = (state, self.unit.now() + self.acting_times.get(state, self.acting_time))
        else:
            self._due = None
        self._executing = state == "Execute"

    def next_poll(self, now: float) -> float:
        """Polled at every tick in Execute (it produces, and counts from its last poll), else only when
        an acting state's time is up (``equipment.PollHint``)."""
        if self._executing:
            return now
        return self._due[1] if self._due is not None else math.inf

    def on_starting(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        self.start_parameters = tuple(parameters)
        self.produced_in_job = 0

    def on_execute(self) -> None:
        self._last_poll = self.unit.now()
        self._executing = True

    def on_clearing(self) -> None:
        self.fault_active = None

    def inject_fault(self, alarm_id: int, message: str, *, value: int = 0) -> None:
        """Simulate an equipment fault: an Alarm, the StopReason, and the unit aborts."""
        self.fault_active = (alarm_id, message)
        self.unit.fault(alarm_id, message, value=value, category=1)

    def poll(self, now: float) -> None:
        if self._due is not None and now >= self._due[1]:
            state, self._due = self._due[0], None
            self.unit.state_complete(state)
        last, self._last_poll = self._last_poll, now
        speed = self.unit.cur_mach_speed
        if last is None or speed <= 0 or now <= last:
            return
        # Accumulate fractions so that counts are exact over time, whatever the poll period.
        self._made += speed / 60.0 * (now - last)
        n = _whole(self._made)
        if n <= 0:
            return
        self._made -= n
        self._defective += n * self.defect_share
        self._consumed += n * self.consumed_per_package
        d, c = _whole(self._defective), _whole(self._consumed)
        self._defective -= d
        self._consumed -= c
        self.unit.report_production(processed=n, defective=d, consumed=c)
        self.produced_in_job += n
        if self.job_size is not None and self.produced_in_job >= self.job_size:
            log.info("simulated job of %d packages done", self.produced_in_job)
            self.unit.equipment_command("ToComplete")


def _whole(x: float) -> int:
    # Tolerate float rounding: 0.1 * 10 steps must count as 1, not 0.
    return int(x + 1e-9)


# What the ``settings`` table of a simulated unit may hold (docs/configuration.md).
SIMULATOR_SETTINGS = ("acting_time", "acting_times", "defect_share", "consumed_per_package", "job_size")


def simulator(spec: Any) -> SimulatedUnit:
    """The equipment factory of a simulated unit (``uacell.packml.sim:simulator``).

    ``spec.settings`` may set ``acting_time`` (seconds per acting state), ``acting_times`` (per state),
    ``defect_share``, ``consumed_per_package`` and ``job_size``.
    """
    settings = dict(spec.settings)
    unknown = sorted(set(settings) - set(SIMULATOR_SETTINGS))
    if unknown:
        raise ValueError(f"the simulator has no setting {unknown[0]!r} (it knows {', '.join(SIMULATOR_SETTINGS)})")
    job_size = settings.get("job_size")
    return SimulatedUnit(
        float(settings.get("acting_time", 0.5)),
        acting_times={str(k): float(v) for k, v in dict(settings.get("acting_times", {})).items()},
        defect_share=float(settings.get("defect_share", 0.02)),
        consumed_per_package=float(settings.get("consumed_per_package", 1.0)),
        job_size=None if job_size is None else int(job_size),
    )
