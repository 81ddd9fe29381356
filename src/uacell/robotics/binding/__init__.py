"""Binds the cell's Robotics controllers to their nodes; one module per concern.

The pure ``RobotCell`` (``uacell.robotics.model``) owns every rule; this package only translates:

- ``core``: one ``RoboticsBinding`` per Controller part (with its TaskControls and motion device,
  its equipment from the factory and settings the configuration names), the shared node helpers,
  coalesced publishing, and the binder ``bind_robotics``;
- ``programs``: ``Controller/Programs``, a ``FileStore`` over ``<data_dir>/programs/<robot>/<controller>``
  (sample programs are installed when that directory does not exist yet) bound by
  ``uacell.binding.file_directory``; the loaded program and modules are protected (Bad_InvalidState on
  delete/overwrite); NodeIds given by clients to LoadByNodeId/UnloadByNodeId;
- ``task_control``: TaskControlStateMachine and ReadySubstateMachine with their methods,
  ``ParameterSet`` values, ``TaskModules`` (one TaskModuleType per loaded module),
  ``MotionDevicesUnderControl`` + a ``Controls`` reference, the stop modes;
- ``system_operation``: SystemOperationStateMachine with its methods and stop modes;
- ``conditions``: the alarm conditions (AlarmConditionType, acknowledgeable, with ActiveState) in
  ``SystemOperation/Conditions``, and the server-specific ``Controller1/SimulateAlarm(String Name,
  Boolean Active)`` (engineer: raise or clear a simulator alarm);
- ``arm``: the motion device's axes (ActualPosition/ActualSpeed/ActualAcceleration) sampled at 10 Hz
  while they change, InControl and OnPath.

``ParameterSet/ExecutionMode`` is writable by operators while the task control is not executing
(Bad_InvalidState otherwise).
"""

from uacell.robotics.binding.core import CONTROLLERS, TASK_CONTROLS, RoboticsBinding, bind_robotics, programs_root
from uacell.robotics.binding.programs import StoreLibrary, install_samples

__all__ = [
    "CONTROLLERS",
    "TASK_CONTROLS",
    "RoboticsBinding",
    "StoreLibrary",
    "bind_robotics",
    "install_samples",
    "programs_root",
]
