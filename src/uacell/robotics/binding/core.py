"""One ``RoboticsBinding`` per Controller part: the shared helpers, publishing, and the binder."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from uacell.binding.cell import BuiltPart
from uacell.core.capabilities import has
from uacell.core.companion import Closer
from uacell.core.drivers import ROBOT_CONTROLLER, SIMULATORS
from uacell.core.equipment_factory import choose_equipment, close_equipment, make_equipment
from uacell.core.errors import ConfigError
from uacell.core.file_store import FileStore
from uacell.core.registry import RegistryKey
from uacell.robotics.binding.arm import Arm
from uacell.robotics.binding.conditions import Conditions
from uacell.robotics.binding.programs import Programs, StoreLibrary, adopt_legacy_programs, install_samples
from uacell.robotics.binding.safety import Safety
from uacell.robotics.binding.shared import Concern, ControllerBinding
from uacell.robotics.binding.system_operation import SystemOperationNodes
from uacell.robotics.binding.task_control import TaskControls
from uacell.robotics.companion import CONTROLLER, MOTION_DEVICE, TASK_CONTROL_PART
from uacell.robotics.config import ControllerSpec, MotionDeviceSpec, RobotConfig, TaskControlSpec
from uacell.robotics.equipment import AxisInfo, ControllerEquipmentSpec, ProgramCatalogue, RobotEquipment, StopMode
from uacell.robotics.model import RobotCell, RoboticsTables, TaskControl
from uacell.robotics.program import ProgramLimits
from uacell.robotics.sim import SimulatedRobot

if TYPE_CHECKING:
    from uacell.host import BinderHost

log = logging.getLogger(__name__)

PROGRAMS_DIR = "programs"
# Every bound controller, keyed by its browse path ("Robot1.Controllers.Controller1").
CONTROLLERS: RegistryKey[RoboticsBinding] = RegistryKey("controller")
# Every task control model, keyed by its browse path ("Robot1.Controllers.Controller1.TaskControls.TaskControl1").
TASK_CONTROLS: RegistryKey[TaskControl] = RegistryKey("task control")


class RoboticsBinding(ControllerBinding):
    """One controller (with its task controls and motion device) on its instance nodes."""

    def compose(self) -> None:
        self._pending = False
        self.programs = Programs(self)
        self.task_controls = TaskControls(self, self.programs)
        self.system_operation = SystemOperationNodes(self)
        self.conditions = Conditions(self)
        self.axes = Arm(self)
        self.safety = Safety(self)
        self.concerns: list[Concern] = [
            self.programs, self.task_controls, self.system_operation, self.conditions, self.axes, self.safety,
        ]  # fmt: skip

    # --- life -----------------------------------------------------------------------------------
    async def setup(self) -> None:
        for concern in self.concerns:
            await concern.setup()
        self.cell.add_listener(self.changed)
        await self.publish()

    def changed(self) -> None:
        # Executable of this controller's methods (only) is re-evaluated when the publisher drains.
        self.app.dispatcher.touch(self.cell)
        # Coalesce: one pending publish job reads the latest model state when it runs.
        if not self._pending:
            self._pending = True
            self.app.publisher.submit(self.publish)

    async def publish(self) -> None:
        self._pending = False
        for concern in self.concerns:
            await concern.publish()

    async def close(self) -> None:
        await self.axes.close()
        await self.cell.close()
        await close_equipment(self.cell.equipment, self.controller.path)
        for concern in self.concerns:
            if concern is not self.axes:
                await concern.close()


# --- the binder ------------------------------------------------------------------------------------
def program_limits(cfg: Any) -> ProgramLimits:
    """The ``[programs]`` section as ``ProgramLimits``."""
    return ProgramLimits(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(ProgramLimits)})


SIMULATOR = SIMULATORS[ROBOT_CONTROLLER]


async def make_controller_equipment(
    app: BinderHost, controller: BuiltPart, axes: tuple[AxisInfo, ...]
) -> RobotEquipment:
    """The controller's own factory and settings, else ``[robot] equipment``, else the simulator."""
    spec = controller.part.spec if isinstance(controller.part.spec, ControllerSpec) else None
    defaults = app.config.section("robot", RobotConfig)
    factory, settings = choose_equipment(
        spec.equipment if spec else "",
        spec.settings if spec else {},
        default=defaults.equipment,
        simulator=SIMULATOR,
        simulator_settings={"time_scale": spec.time_scale if spec else None},
        simulator_defaults={"time_scale": defaults.time_scale},
    )
    equipment: RobotEquipment = await make_equipment(
        factory, ControllerEquipmentSpec(controller.path, settings, axes), RobotEquipment
    )
    if axes and len(equipment.axes) != len(axes):
        await close_equipment(equipment, controller.path)
        raise ConfigError(
            f"{controller.path}: equipment {factory!r} reports {len(equipment.axes)} axes,"
            f" the motion device it moves has {len(axes)}"
        )
    return equipment


def _arm_of(app: BinderHost, controller: BuiltPart) -> BuiltPart | None:
    """The motion device the controller moves: the configured one, else the robot's first."""
    system_path = controller.path.split(".Controllers.")[0]
    arms = [m for m in app.cell.by_role(MOTION_DEVICE) if m.path.startswith(system_path + ".")]
    spec = controller.part.spec
    if isinstance(spec, ControllerSpec):
        return next((m for m in arms if m.part.name == spec.motion_device), None)
    return arms[0] if arms else None


def programs_root(data_dir: Path, controller_path: str) -> Path:
    """``<data_dir>/programs/<robot>/<controller>``: its own for every controller of the cell."""
    robot, _, name = controller_path.partition(".Controllers.")
    return Path(data_dir) / PROGRAMS_DIR / robot / name


async def bind_controller(app: BinderHost, controller: BuiltPart, tables: RoboticsTables) -> RoboticsBinding:
    """One controller with its task controls and motion device, on its own equipment and Programs."""

    tasks = [t for t in app.cell.by_role(TASK_CONTROL_PART) if t.path.startswith(controller.path + ".")]
    arm = _arm_of(app, controller)
    axes = tuple(arm.part.spec.axes) if arm is not None and isinstance(arm.part.spec, MotionDeviceSpec) else ()
    spec = controller.part.spec if isinstance(controller.part.spec, ControllerSpec) else None
    equipment = await make_controller_equipment(app, controller, axes)
    bounds = program_limits(app.config.programs)
    if isinstance(equipment, SimulatedRobot):
        equipment.program_limits = bounds  # the simulator expands programs within the same bounds
    root = programs_root(app.data_dir, controller.path)
    robots = sorted({c.path.partition(".Controllers.")[0] for c in app.cell.by_role(CONTROLLER)})
    if controller is app.cell.by_role(CONTROLLER)[0]:
        adopt_legacy_programs(root.parent.parent, root, robots)
    if has(equipment, ProgramCatalogue):  # the controller holds its programs: no samples
        root.mkdir(parents=True, exist_ok=True)
    else:
        install_samples(root, equipment.axes, moves=arm is not None)
    store = FileStore(root, max_bytes=app.config.programs.max_folder_bytes, handles=app.file_handles)
    library = StoreLibrary(store)
    library.max_bytes = bounds.max_file_bytes
    cell = RobotCell(
        equipment,
        library,
        tables=tables,
        bounds=bounds,
        task_names=[t.part.name for t in tasks],
        motion_devices=[arm.part.name] if arm else (),
        possible_stop_modes=spec.possible_stop_modes if spec else tuple(StopMode),
        default_stop_mode=spec.default_stop_mode if spec else StopMode.ON_PATH,
    )
    for t in tasks:
        if isinstance(t.part.spec, TaskControlSpec):
            cell.tasks[t.part.name].execution_mode = t.part.spec.execution_mode
    binding = RoboticsBinding(app, controller, tasks, arm, cell, store)
    await binding.setup()
    return binding


async def bind_robotics(app: BinderHost) -> Closer | None:
    """Bind every controller of the cell (role ``controller``) with its task controls and arm."""
    controllers = app.cell.by_role(CONTROLLER)
    if not controllers:
        return None
    tables = RoboticsTables.load(app.tables)
    bindings: list[RoboticsBinding] = []

    async def close() -> None:
        for b in bindings:
            await b.close()

    try:
        for controller in controllers:
            binding = await bind_controller(app, controller, tables)
            bindings.append(binding)
            app.registry(CONTROLLERS).add(controller.path, binding)
            for task in binding.task_parts.values():
                app.registry(TASK_CONTROLS).add(task.path, binding.cell.tasks[task.part.name])
    except BaseException:
        await close()  # the drivers already connected
        raise
    return close
