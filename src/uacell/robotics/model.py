"""OPC 40010-1 remote operation, free of OPC UA: TaskControl, SystemOperation and the cell wiring them.

The rules are docs/decisions.md 8-21 (docs/robotics.md is the client's view of them). State lives
only in ``uacell.fsm.StateMachine`` objects built from the NodeSet tables; the OPC UA binding
listens to them and to ``listeners`` (called after any other observable change) and publishes.
Operations return the Int32 ``Status`` of the Robotics methods, or raise ``CallError`` for Bad codes.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields
from enum import IntEnum
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Protocol

from uacell.background import Background
from uacell.conditions import ConditionSet
from uacell.errors import CallError
from uacell.files import settled, stamp
from uacell.fsm import Reason, StateMachine
from uacell.models import FsmTable, TableLoader
from uacell.robotics.equipment import (
    AlarmReset,
    AlarmStop,
    ConfirmedStart,
    EquipmentError,
    ExecutionMode,
    PowerFeedback,
    ProgramCatalogue,
    ProgramRejected,
    RobotEquipment,
    RunOutcome,
    StartRefused,
    StopMode,
    UnknownProgram,
)
from uacell.robotics.program import (
    DEFAULT_LIMITS,
    Kind,
    NothingToExecute,
    Program,
    ProgramError,
    ProgramLimits,
    ProgramTooLarge,
    measure,
    parse,
)

log = logging.getLogger(__name__)

PROGRAM_SUFFIX = ".robot"


class Status(IntEnum):
    """Values of the Robotics methods' Int32 ``Status`` output (negative: uacell vendor codes)."""

    OK = 0
    E_SYSTEM_STATE = 1
    E_UNEXPECTED_ERROR = 2
    E_ACTIVE_ALARM = 3
    E_ACKNOWLEDGE_REQUIRED = 4
    NOT_FOUND = -1  # no such program/module file (load), or not loaded (unload)
    INVALID_CONTENT = -2  # the file is not a valid program or module
    UNRESOLVED_REFERENCE = -3  # Start: a used module is not loaded, or a called routine is missing
    MODULE_REFERENCED = -4  # unload of a module the program or another module uses


# --- the NodeSet's names ----------------------------------------------------------------------------
# Machines (BrowseNames of the instance machines) and their states, as OPC 40010-1 names them.
# ``RoboticsTables`` checks every one against the NodeSet when the tables are loaded; transitions are
# never named: they are looked up in the table by cause (method) or by from/to state.
TASK_CONTROL = "TaskControlStateMachine"
READY_SUB = "ReadySubstateMachine"
SYSTEM_OPERATION = "SystemOperationStateMachine"
IDLE_SUB = "IdleSubstateMachine"
EXECUTING_SUB = "ExecutingSubstateMachine"
IDLE, READY, EXECUTING = "Idle", "Ready", "Executing"  # TaskControl and SystemOperation
AT_PROGRAM_START, SUSPENDED = "AtProgramStart", "Suspended"  # ReadySubstateMachineType
STAND_BY, GETTING_READY = "StandBy", "GettingReady"  # IdleSubstateMachineType
RUNNING, STOPPING = "Running", "Stopping"  # ExecutingSubstateMachineType

# Calls that act in a state without taking a transition (docs/decisions.md 11, 15, 16): the one place
# Robotics adds to the NodeSet's HasCause table. Everything else a method may do, the table says.
STAYS: frozenset[tuple[str, str]] = frozenset(
    {
        ("LoadByName", READY),  # 11: replaces the program or adds a module
        ("LoadByNodeId", READY),
        ("UnloadByName", IDLE),  # 15: a module loaded without a program
        ("UnloadByNodeId", IDLE),
        ("ResetToProgramStart", AT_PROGRAM_START),  # 16: Status 0, no transition
    }
)


@dataclass(frozen=True)
class RoboticsTables:
    """The five Robotics state-machine tables, handed to the models by whoever knows the NodeSets."""

    task_control: FsmTable
    ready: FsmTable
    system_operation: FsmTable
    idle: FsmTable
    executing: FsmTable

    @classmethod
    def load(cls, tables: TableLoader) -> RoboticsTables:
        """Read the tables through ``tables`` and check every name this module uses against them."""
        loaded = cls(
            task_control=tables("Robotics", "TaskControlStateMachineType"),
            ready=tables("Robotics", "ReadySubstateMachineType"),
            system_operation=tables("Robotics", "SystemOperationStateMachineType"),
            idle=tables("Robotics", "IdleSubstateMachineType"),
            executing=tables("Robotics", "ExecutingSubstateMachineType"),
        )
        loaded.task_control.check_names((IDLE, READY, EXECUTING))
        loaded.ready.check_names((AT_PROGRAM_START, SUSPENDED))
        loaded.system_operation.check_names((IDLE, READY, EXECUTING))
        loaded.idle.check_names((STAND_BY, GETTING_READY))
        loaded.executing.check_names((RUNNING, STOPPING))
        every = {m for f in fields(cls) for m in getattr(loaded, f.name).methods}
        unknown = sorted({m for m, _ in STAYS} - every)
        if unknown:
            raise LookupError(f"the Robotics NodeSet has no method {', '.join(unknown)}")
        return loaded


# --- where programs come from ---------------------------------------------------------------------
class ProgramLibrary(Protocol):
    """The programs and modules available to load (the Controller's ``Programs`` folder)."""

    def names(self) -> list[str]:
        """Names LoadByName accepts."""
        ...

    def resolve(self, name: str) -> str | None:
        """The relative path of the file called ``name``, or None."""
        ...

    def read(self, relpath: str) -> str:
        """The file's text; ``FileNotFoundError`` if there is none, ``OSError`` if it cannot be read."""
        ...

    # Optional: ``read_small(relpath) -> str | None``, the text of a file of at most
    # INLINE_PROGRAM_BYTES and None for a larger one, lets small files be read on the event loop
    # instead of in a worker thread.


# Programs up to this size are read and checked on the event loop (about 70 us a KiB here); larger
# ones in a worker thread, so that a big file never holds up other clients' requests.
INLINE_PROGRAM_BYTES = 4096
KEPT_TEXTS = 64  # the texts of small programs a library keeps (``DirectoryLibrary.read``)


class DirectoryLibrary:
    """Programs stored as ``*.robot`` files in a directory tree; a file's name is its stem.

    ``read`` reads at most ``max_bytes`` (``ProgramTooLarge`` beyond) and decodes UTF-8 strictly.
    """

    def __init__(self, root: Path | str, *, max_bytes: int = DEFAULT_LIMITS.max_file_bytes) -> None:
        self.root = Path(root)
        self.max_bytes = max_bytes
        self._texts: dict[str, tuple[tuple[int, int, int, int], str]] = {}  # relpath -> (stamp, text)

    def _files(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.rglob(f"*{PROGRAM_SUFFIX}") if p.is_file())

    def names(self) -> list[str]:
        return sorted({p.stem for p in self._files()})

    def resolve(self, name: str) -> str | None:
        # Sorted paths make the choice stable when two subdirectories hold the same name.
        for p in self._files():
            if p.stem == name:
                return p.relative_to(self.root).as_posix()
        return None

    def _path(self, relpath: str) -> str:
        rel = PurePosixPath(relpath)
        if rel.is_absolute() or ".." in rel.parts:
            raise FileNotFoundError(relpath)
        return os.path.join(self.root, relpath)

    def read_small(self, relpath: str) -> str | None:
        """``read`` for a file of at most INLINE_PROGRAM_BYTES; None for a larger one, or one whose
        size cannot be known (``read`` then says why)."""
        return self._read(relpath, small=True)

    def read(self, relpath: str) -> str:
        """The file's text. A small file's text is kept while its status (inode, size, times) is what it
        was when read, and it had not changed for two seconds then (``files.settled``): loading the
        same program again costs one ``stat``, not a read and a decode."""
        text = self._read(relpath, small=False)
        assert text is not None
        return text

    def _read(self, relpath: str, small: bool) -> str | None:
        path = self._path(relpath)
        try:
            st: os.stat_result | None = os.stat(path)
        except OSError:
            st = None  # open says why
        if small and (st is None or st.st_size > INLINE_PROGRAM_BYTES):
            return None
        kept = self._texts.get(relpath)
        if kept is not None and st is not None and kept[0] == stamp(st):
            return kept[1]
        with open(path, "rb") as f:
            data = f.read(self.max_bytes + 1)
        if len(data) > self.max_bytes:
            raise ProgramTooLarge(0, f"the file is larger than {self.max_bytes} bytes")
        text = data.decode("utf-8")
        self._texts.pop(relpath, None)
        if st is not None and st.st_size == len(data) <= INLINE_PROGRAM_BYTES and settled(st):
            if len(self._texts) >= KEPT_TEXTS:
                self._texts.pop(next(iter(self._texts)), None)  # the oldest
            self._texts[relpath] = (stamp(st), text)
        return text


# --- observable data -------------------------------------------------------------------------------
@dataclass(frozen=True)
class TaskModule:
    """A module loaded on a task control (TaskModuleType: Name, Version, IsReferenced)."""

    name: str
    version: str
    is_referenced: bool
    relpath: str | None


Listener = Callable[[], None]
_UNKNOWN = object()


class _Failure(Exception):
    def __init__(self, status: Status, reason: str) -> None:
        super().__init__(reason)
        self.status = status


def _resolve_stop_mode(value: int, possible: Sequence[StopMode], default: StopMode) -> StopMode:
    if value == 0:
        return default
    if value not in [int(m) for m in possible]:
        raise CallError("BadInvalidArgument", f"StopMode {value} is not in PossibleStopModes", argument=0)
    return StopMode(value)


def _notify(listeners: Iterable[Listener]) -> None:
    for listener in list(listeners):
        listener()


class _Guarded:
    """The one refusal path of a Robotics object (docs/decisions.md 4 and 8).

    A method may act when its machine ``allows`` it (the NodeSet's HasCause table plus ``STAYS``) and
    the method's entry in ``_conditions`` (if any) has no objection. Operations answer the Status this
    returns; ``Executable`` is true exactly when it returns None.
    """

    _machines: dict[str, StateMachine]
    _conditions: dict[str, Callable[[], Status | None]]

    equipment: RobotEquipment

    def _refusal(self, machine_name: str, method: str) -> Status | None:
        """Why ``method`` of machine ``machine_name`` cannot act now (a Status), or None if it can.

        Equipment that says it cannot reach its controller (``reachable`` false, e.g. the gateway's
        drivers) refuses every method with Bad_CommunicationError (a CallError): nothing is tried.
        """
        if not getattr(self.equipment, "reachable", True):
            raise CallError("BadCommunicationError", "the robot controller cannot be reached")
        machine = self._machines.get(machine_name)
        if machine is None or method not in machine.table.methods or not machine.allows(method, STAYS):
            return Status.E_SYSTEM_STATE
        condition = self._conditions.get(method)
        return condition() if condition is not None else None

    def executable(self, machine_name: str, method: str) -> bool:
        try:
            return self._refusal(machine_name, method) is None
        except CallError:
            return False

    def methods(self) -> list[tuple[str, str]]:
        """Every (machine name, method) the NodeSet gives this object's machines."""
        return [(name, m) for name, machine in self._machines.items() for m in sorted(machine.table.methods)]


# --- a controller that keeps its programs and confirms its starts (decision 70) --------------------
class _OnController(_Guarded):
    """What TaskControl does for equipment that keeps its own programs (``ProgramCatalogue``) and
    confirms its starts (``ConfirmedStart``)."""

    name: str
    equipment: RobotEquipment
    machine: StateMachine
    pointer: int
    execution_mode: ExecutionMode
    last_error: str
    _lock: asyncio.Lock
    _modules: dict[str, tuple[Program, str | None]]

    if TYPE_CHECKING:  # TaskControl's

        def _load_failed(self, status: Status, reason: str) -> int: ...
        def _fail(self, status: Status, reason: str) -> int: ...
        def _take_program(self, program: Program, relpath: str | None, on_controller: bool = False) -> None: ...
        def _start_problem(self) -> Status | None: ...
        def _go(self, reason: Reason) -> int: ...

    async def load_controller_program(self, name: str) -> int:
        """LoadByNodeId, after the binding resolved the NodeId to a program the controller holds."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "LoadByNodeId")) is not None:
                return problem
            return await self._select(name)

    async def _select(self, name: str) -> int:
        """Select the controller's own program ``name`` (a ``ProgramCatalogue``): no file, no text;
        what it calls is the controller's business (Start never answers -3 for it)."""
        assert isinstance(self.equipment, ProgramCatalogue)
        if name in self._modules:
            return self._load_failed(Status.INVALID_CONTENT, f"program {name} has a loaded module's name")
        try:
            await self.equipment.select(self.name, name)
        except UnknownProgram as e:
            return self._load_failed(Status.NOT_FOUND, f"the controller has no program {name!r}: {e}")
        except ProgramRejected as e:
            return self._load_failed(Status.INVALID_CONTENT, f"the controller rejected {name!r}: {e}")
        except EquipmentError as e:
            return self._load_failed(Status.E_UNEXPECTED_ERROR, f"the controller could not select {name!r}: {e}")
        if self.machine.current == EXECUTING:
            return self._load_failed(Status.E_SYSTEM_STATE, "task control started during load")
        self.last_error = ""
        self._take_program(Program(name, Kind.PROGRAM, "", (), ()), None, on_controller=True)
        return Status.OK

    async def _start_confirmed(self, reason: Reason) -> int:
        """Start on a controller that confirms it: Executing once it runs; a refusal answers at once
        (StartRefused: 1, a fault: 3, another failure: 2) and changes nothing. Loads wait meanwhile,
        a second Start answers 1."""
        assert isinstance(self.equipment, ConfirmedStart)
        if (problem := self._start_problem()) is not None:
            return problem
        async with self._lock:
            try:
                await self.equipment.begin(self.name, self.pointer, self.execution_mode)
            except StartRefused as e:
                return self._fail(Status.E_SYSTEM_STATE, f"the controller refused the start: {e}")
            except AlarmStop as e:
                return self._fail(Status.E_ACTIVE_ALARM, f"the controller refused the start: {e}")
            except EquipmentError as e:
                return self._fail(Status.E_UNEXPECTED_ERROR, f"the controller did not start: {e}")
            return self._go(reason)


# --- TaskControl -----------------------------------------------------------------------------------
class TaskControl(_OnController):
    """One task control: loads programs and modules, runs them on the equipment (TaskControlStateMachine)."""

    def __init__(
        self,
        name: str,
        equipment: RobotEquipment,
        library: ProgramLibrary,
        *,
        tables: RoboticsTables,
        system: SystemOperation | None = None,
        motion_devices: Sequence[str] = ("Arm1",),
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
        execution_mode: ExecutionMode = ExecutionMode.CYCLE,
        bounds: ProgramLimits = DEFAULT_LIMITS,
    ) -> None:
        self.name = name
        self.equipment = equipment
        self.library = library
        self.bounds = bounds
        self._parsed: dict[tuple[str, tuple[tuple[float, float], ...], ProgramLimits], Program] = {}
        self.system = system
        self.motion_devices = tuple(motion_devices)
        self.possible_stop_modes = tuple(possible_stop_modes)
        self.default_stop_mode = default_stop_mode
        self.execution_mode = execution_mode
        self.machine = StateMachine(TASK_CONTROL, tables.task_control, IDLE)
        self.ready = StateMachine(READY_SUB, tables.ready, AT_PROGRAM_START, parent=self.machine, parent_state=READY)
        self._machines = {m.name: m for m in self.machine.walk()}
        # What a method needs beyond the table (None: nothing more, else the Status to answer).
        self._conditions: dict[str, Callable[[], Status | None]] = {
            "Start": self._start_conditions,
            "Stop": lambda: Status.E_SYSTEM_STATE if self.stopping else None,
            "UnloadByName": self._something_loaded,
            "UnloadByNodeId": self._something_loaded,
        }
        self.program: Program | None = None
        self.program_file: str | None = None
        self.on_controller = False  # the program is the controller's own (no file, no text)
        self._modules: dict[str, tuple[Program, str | None]] = {}
        self.pointer = 0  # index of the next step to execute
        self.current_line = 0  # source line of the instruction being executed (0: none)
        self.last_error = ""  # why the last operation failed, for logs and diagnostics
        self.stopping = False
        self._stop_context: contextvars.Context | None = None  # the Stop call that is stopping the run
        self.listeners: list[Listener] = []
        self._lock = asyncio.Lock()
        self._bg = Background()
        self._run: asyncio.Task[None] | None = None
        self._resolution: object = _UNKNOWN
        if system is not None:
            system.add_task(self)

    def __repr__(self) -> str:
        return f"<TaskControl {self.name} {self.machine.current} {self.program_name!r}>"

    # observable data
    @property
    def program_name(self) -> str:
        return self.program.name if self.program else ""

    @property
    def program_loaded(self) -> bool:
        return self.program is not None

    @property
    def modules(self) -> list[TaskModule]:
        used: set[str] = set(self.program.uses) if self.program else set()
        for module, _ in self._modules.values():
            used.update(module.uses)
        return [TaskModule(m.name, m.version, m.name in used, rel) for m, rel in self._modules.values()]

    @property
    def state(self) -> str:
        return self.machine.current

    @property
    def executing(self) -> bool:
        return self.machine.current == EXECUTING

    def machines(self) -> list[StateMachine]:
        return self.machine.walk()

    def _changed(self) -> None:
        self._resolution = _UNKNOWN
        _notify(self.listeners)
        if self.system is not None:
            self.system._changed()

    def _something_loaded(self) -> Status | None:
        return Status.E_SYSTEM_STATE if self.program is None and not self._modules else None

    # loading
    async def load_by_name(self, name: str) -> int:
        """LoadByName: a program or module from the library by file name (without extension)."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "LoadByName")) is not None:
                return problem
            relpath = self.library.resolve(name)
            if relpath is not None:  # a file in Programs: uacell holds the text (also on a gateway robot)
                return await self._load(relpath)
            catalogue = self.equipment if isinstance(self.equipment, ProgramCatalogue) else None
            found = catalogue.find_program(name) if catalogue is not None else None
            if found is None:
                return self._load_failed(Status.NOT_FOUND, f"no program or module named {name!r}")
            return await self._select(found)

    async def load_file(self, relpath: str) -> int:
        """LoadByNodeId, after the binding resolved the NodeId to a file in Programs."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "LoadByNodeId")) is not None:
                return problem
            return await self._load(relpath)

    def _read_and_check(
        self, relpath: str, modules: dict[str, Program], read: Callable[[str], str | None] | None = None
    ) -> Program | None:
        """Read, parse and measure ``relpath`` (in a worker thread: bounded by ``self.bounds``), read
        with ``read`` when given (None from it: not read, nothing checked: None)."""
        try:
            text = (read or self.library.read)(relpath)
            if text is None:
                return None
        except FileNotFoundError:
            raise _Failure(Status.NOT_FOUND, f"no file {relpath!r}") from None
        except ProgramError as e:
            raise _Failure(Status.INVALID_CONTENT, f"{relpath}: {e}") from e
        except UnicodeDecodeError as e:
            raise _Failure(Status.INVALID_CONTENT, f"{relpath}: not UTF-8 text ({e.reason} at byte {e.start})") from e
        except OSError as e:
            raise _Failure(Status.E_UNEXPECTED_ERROR, f"cannot read {relpath!r}: {e}") from e
        try:
            # No motion device (motion_device = ""): nothing to move, a 'move' is refused (decision 33).
            limits = tuple(a.limits for a in self.equipment.axes) if self.motion_devices else ()
            key = (text, limits, self.bounds)
            program = self._parsed.get(key)
            if program is None:
                program = parse(text, limits, bounds=self.bounds)
                if len(text) <= INLINE_PROGRAM_BYTES:  # a Program is immutable: the same text, the same one
                    if len(self._parsed) >= KEPT_TEXTS:
                        self._parsed.pop(next(iter(self._parsed)), None)
                    self._parsed[key] = program
            # What can be known before Start: the file alone (and the modules loaded now) is within bounds.
            measure(program, modules, self.bounds, partial=True)
        except ProgramError as e:
            raise _Failure(Status.INVALID_CONTENT, f"{relpath}: {e}") from e
        return program

    async def _load(self, relpath: str) -> int:
        try:
            modules = {n: m for n, (m, _) in self._modules.items()}
            # ``read_small`` is optional for a library (DirectoryLibrary has it): a small file is read
            # and checked on the loop (a few hundred microseconds at most), anything else in a thread.
            small = getattr(self.library, "read_small", None)
            program = self._read_and_check(relpath, modules, small) if small is not None else None
            if program is None:
                program = await asyncio.to_thread(self._read_and_check, relpath, modules)
            assert program is not None  # read by the library's ``read``: a text or an error
            if program.kind is Kind.MODULE and self.program is not None and program.name == self.program.name:
                raise _Failure(Status.INVALID_CONTENT, f"module {program.name} has the program's name")
            if program.kind is Kind.PROGRAM and program.name in self._modules:
                raise _Failure(Status.INVALID_CONTENT, f"program {program.name} has a loaded module's name")
            try:
                await self.equipment.load(self.name, program)
            except ProgramRejected as e:
                raise _Failure(Status.INVALID_CONTENT, f"controller rejected {relpath}: {e}") from e
            except EquipmentError as e:
                raise _Failure(Status.E_UNEXPECTED_ERROR, f"controller could not load {relpath}: {e}") from e
        except _Failure as f:
            return self._load_failed(f.status, str(f))
        except CallError:  # the controller answered with a code (Bad_Timeout, Bad_CommunicationError): nothing changed
            raise
        except Exception as e:  # a bug in a library or equipment must not leave the machine half-done
            log.exception("%s: loading %s failed", self.name, relpath)
            return self._load_failed(Status.E_UNEXPECTED_ERROR, f"internal error: {e}")
        if self.machine.current == EXECUTING:  # a run started while the controller was loading
            return self._load_failed(Status.E_SYSTEM_STATE, "task control started during load")
        self.last_error = ""
        if program.kind is Kind.MODULE:
            # Replacing a module the program uses changes the executed steps: a suspended pointer
            # would resume at an unrelated instruction, so the program goes back to its start.
            replaces_used = any(m.name == program.name and m.is_referenced for m in self.modules)
            self._modules[program.name] = (program, relpath)
            log.info("%s: loaded module %s %s", self.name, program.name, program.version)
            if replaces_used and self.ready.is_in(SUSPENDED):
                self.pointer, self.current_line = 0, 0
                self.ready.move(AT_PROGRAM_START, Reason.EXTERNAL)
            self._changed()
            return Status.OK
        self._take_program(program, relpath)
        return Status.OK

    def _take_program(self, program: Program, relpath: str | None, on_controller: bool = False) -> None:
        self.program, self.program_file, self.pointer, self.current_line = program, relpath, 0, 0
        self.on_controller = on_controller
        log.info("%s: loaded program %s %s", self.name, program.name, program.version or "(on the controller)")
        if self.machine.current == IDLE:
            self.machine.move(READY, Reason.EXTERNAL)
            self.ready.enter(AT_PROGRAM_START, Reason.EXTERNAL)
        elif self.ready.current == SUSPENDED:
            self.ready.move(AT_PROGRAM_START, Reason.EXTERNAL)
        self._changed()

    def _load_failed(self, status: Status, reason: str) -> int:
        self.last_error = reason
        log.warning("%s: load failed (Status %d): %s", self.name, status, reason)
        if self.machine.current == IDLE and status != Status.E_SYSTEM_STATE:
            self.machine.move(IDLE, Reason.ERROR)
        self._changed()
        return status

    # unloading
    async def unload_program(self) -> int:
        """UnloadProgram: the program and all modules; Ready -> Idle."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "UnloadProgram")) is not None:
                return problem
            return await self._unload_all()

    async def unload_by_name(self, name: str) -> int:
        """UnloadByName: the program (as UnloadProgram) or one module."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "UnloadByName")) is not None:
                return problem
            if self.program is not None and name == self.program.name:
                return await self._unload_all()
            return await self._unload_module(name)

    async def unload_by_file(self, relpath: str) -> int:
        """UnloadByNodeId with the FileType node of a loaded program or module."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "UnloadByNodeId")) is not None:
                return problem
            if self.program is not None and self.program_file == relpath:
                return await self._unload_all()
            for program, rel in self._modules.values():
                if rel == relpath:
                    return await self._unload_module(program.name)
            return self._fail(Status.NOT_FOUND, f"{relpath} is not loaded")

    async def unload_module(self, name: str) -> int:
        """UnloadByNodeId with a TaskModule node."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "UnloadByNodeId")) is not None:
                return problem
            return await self._unload_module(name)

    async def _unload_all(self) -> int:
        assert self.program is not None
        try:
            for module in list(self._modules):
                await self.equipment.unload(self.name, module)
                del self._modules[module]
            await self.equipment.unload(self.name, self.program.name)
        except EquipmentError as e:
            self._changed()
            return self._fail(Status.E_UNEXPECTED_ERROR, f"controller could not unload: {e}")
        log.info("%s: unloaded program %s", self.name, self.program.name)
        self.program, self.program_file, self.pointer, self.current_line = None, None, 0, 0
        self.on_controller = False
        self.machine.move(IDLE, Reason.EXTERNAL)
        self._changed()
        return Status.OK

    async def _unload_module(self, name: str) -> int:
        found = next((m for m in self.modules if m.name == name), None)
        if found is None:
            return self._fail(Status.NOT_FOUND, f"{name} is not loaded")
        if found.is_referenced:
            return self._fail(Status.MODULE_REFERENCED, f"module {name} is in use")
        try:
            await self.equipment.unload(self.name, name)
        except EquipmentError as e:
            return self._fail(Status.E_UNEXPECTED_ERROR, f"controller could not unload {name}: {e}")
        del self._modules[name]
        log.info("%s: unloaded module %s", self.name, name)
        self._changed()
        return Status.OK

    def _fail(self, status: Status, reason: str) -> int:
        self.last_error = reason
        log.warning("%s: Status %d: %s", self.name, status, reason)
        return status

    # running
    def _start_check(self) -> Status | None:
        """Why Start would fail now (None: it can succeed)."""
        return self._refusal(TASK_CONTROL, "Start")

    def _start_conditions(self) -> Status | None:
        if self.program is None or self._lock.locked():
            return Status.E_SYSTEM_STATE
        if self.system is not None:
            if not self.system.allows_task_start():
                return Status.E_SYSTEM_STATE
            alarm = self.system.alarm_status()
            if alarm is not None:
                return alarm
        if isinstance(self.equipment, ConfirmedStart) and self.equipment.start_refusal() is not None:
            return Status.E_SYSTEM_STATE  # the controller would refuse it: nothing is sent
        problem = self._unresolved()
        if isinstance(problem, ProgramTooLarge | NothingToExecute):
            return Status.INVALID_CONTENT
        if problem is not None:
            return Status.UNRESOLVED_REFERENCE
        return None

    def _unresolved(self) -> ProgramError | None:
        """Why the program's calls do not resolve against the loaded modules (cached per load/unload)."""
        if self._resolution is _UNKNOWN:
            self._resolution = None
            if self.program is not None and not self.on_controller:
                try:
                    measure(self.program, {n: m for n, (m, _) in self._modules.items()}, self.bounds)
                except ProgramError as e:
                    self._resolution = e
        return self._resolution  # type: ignore[return-value]

    async def start(self) -> int:
        """Start: Ready -> Executing, from the program start or where it was suspended; on equipment
        that confirms starts (``ConfirmedStart``) once the controller confirmed it."""
        if isinstance(self.equipment, ConfirmedStart):
            return await self._start_confirmed(Reason.EXTERNAL)
        return self._start(Reason.EXTERNAL)

    def _start_problem(self) -> Status | None:
        problem = self._start_check()
        if problem is not None:
            if problem in (Status.UNRESOLVED_REFERENCE, Status.INVALID_CONTENT):
                return Status(self._fail(problem, str(self._unresolved())))
            refusal = self.equipment.start_refusal() if isinstance(self.equipment, ConfirmedStart) else None
            why = f"the controller would refuse the start: {refusal}" if refusal else f"cannot start in {self.state}"
            return Status(self._fail(problem, why))
        return None

    def _start(self, reason: Reason) -> int:
        if (problem := self._start_problem()) is not None:
            return problem
        return self._go(reason)

    def _go(self, reason: Reason) -> int:
        self.stopping = False
        self._stop_context = None
        self.machine.move(EXECUTING, reason)
        mode = self.execution_mode
        log.info("%s: started %s at step %d (%s)", self.name, self.program_name, self.pointer, mode.name)
        self._run = self._bg.spawn(self._execute(self.pointer, self.execution_mode))
        if self.system is not None:
            self.system._task_started(self)
        self._changed()
        return Status.OK

    async def _execute(self, pointer: int, mode: ExecutionMode) -> None:
        reason: Reason
        try:
            outcome = await self.equipment.run(self.name, pointer, mode, self._progress)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # EquipmentError or a bug: the program stays loaded, the robot is still
            if not isinstance(e, EquipmentError):
                log.exception("%s: run failed", self.name)
            self.last_error = f"run ended by a fault: {e}"
            log.warning("%s: %s", self.name, self.last_error)
            outcome, reason = RunOutcome(self.pointer, False), Reason.ERROR
        else:
            if self.stopping:
                reason = Reason.EXTERNAL
            elif outcome.completed:
                reason = Reason.APPLICATION
            else:
                reason = Reason.SYSTEM  # a STEP done, or the controller stopped by itself
        stop, self._stop_context = self._stop_context, None
        if stop is not None and self.stopping:
            stop.run(self._finish, outcome, reason)  # in the Stop call's context: its audit event
        else:
            self._finish(outcome, reason)

    def _progress(self, pointer: int, line: int) -> None:
        self.pointer, self.current_line = pointer, line
        _notify(self.listeners)

    def _finish(self, outcome: RunOutcome, reason: Reason) -> None:
        stopped = self.stopping
        self.stopping = False
        self.pointer, self.current_line = outcome.pointer, 0
        self.machine.move(READY, reason)
        # Decision 16: after Stop, Suspended; after the program ended by itself, AtProgramStart.
        at_start = outcome.completed and not stopped and reason != Reason.ERROR
        self.ready.enter(AT_PROGRAM_START if at_start else SUSPENDED, reason)
        log.info("%s: %s is Ready (%s, step %d)", self.name, self.program_name, reason.name, self.pointer)
        if self.system is not None:
            self.system._task_finished(self, reason)
        self._changed()

    async def stop(self, stop_mode: int) -> int:
        """Stop: accepted at once (Status 0); ExecutingToReady follows when the robot has stopped."""
        mode = _resolve_stop_mode(stop_mode, self.possible_stop_modes, self.default_stop_mode)
        return await self._stop(mode)

    async def _stop(self, mode: StopMode, system_reason: Reason = Reason.SYSTEM) -> int:
        if (problem := self._refusal(TASK_CONTROL, "Stop")) is not None:
            return problem
        self.stopping = True
        try:
            await self.equipment.stop(self.name, mode)
        except EquipmentError as e:
            self.stopping = False
            return self._fail(Status.E_UNEXPECTED_ERROR, f"controller could not stop: {e}")
        log.info("%s: stopping (%s)", self.name, mode.name)
        # ExecutingToReady follows once the robot has stopped: the caller's (decision 38).
        self._stop_context = contextvars.copy_context()
        if self.system is not None and self.executing:  # the run may have ended while the stop was asked
            self.system._task_stopping(system_reason)
        self._changed()
        return Status.OK

    async def reset_to_program_start(self) -> int:
        """ResetToProgramStart: in Ready, move the program pointer to the start."""
        if (problem := self._refusal(READY_SUB, "ResetToProgramStart")) is not None:
            return problem
        self.pointer, self.current_line = 0, 0
        if self.ready.current == SUSPENDED:
            self.ready.move(AT_PROGRAM_START, Reason.EXTERNAL)
            self._changed()
        return Status.OK

    async def set_execution_mode(self, mode: int) -> int:
        """Change ExecutionMode (CYCLE 0, CONTINUOUS 1, STEP 2); not while Executing."""
        if mode not in [int(m) for m in ExecutionMode]:
            raise CallError("BadInvalidArgument", f"ExecutionMode {mode} is unknown", argument=0)
        if self.machine.current == EXECUTING:
            return Status.E_SYSTEM_STATE
        self.execution_mode = ExecutionMode(mode)
        self._changed()
        return Status.OK

    async def wait_until_not_executing(self) -> None:
        """Wait for a running program (if any) to end and the machine to leave Executing."""
        if self._run is not None:
            await asyncio.wait({self._run})

    async def close(self) -> None:
        await self._bg.close()


# --- SystemOperation -------------------------------------------------------------------------------
class SystemOperation(_Guarded, ConditionSet):
    """The robot system's power state and alarms (SystemOperationStateMachine), coupled to task controls;
    its conditions are SystemOperation/Conditions (decision 18)."""

    def __init__(
        self,
        equipment: RobotEquipment,
        *,
        tables: RoboticsTables,
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
    ) -> None:
        self.equipment = equipment
        self.possible_stop_modes = tuple(possible_stop_modes)
        self.default_stop_mode = default_stop_mode
        self.machine = StateMachine(SYSTEM_OPERATION, tables.system_operation, IDLE)
        self.idle = StateMachine(IDLE_SUB, tables.idle, STAND_BY, parent=self.machine, parent_state=IDLE)
        self.executing = StateMachine(
            EXECUTING_SUB, tables.executing, RUNNING, parent=self.machine, parent_state=EXECUTING
        )
        self._machines = {m.name: m for m in self.machine.walk()}
        # What a method needs beyond the table (None: nothing more, else the Status to answer).
        self._conditions: dict[str, Callable[[], Status | None]] = {
            "GetReady": self._get_ready_conditions,
            "StandDown": self._stand_down_conditions,
            "Start": self._start_conditions,
            "Stop": lambda: None if self.executing.is_in(RUNNING) else Status.E_SYSTEM_STATE,
        }
        self.tasks: list[TaskControl] = []
        ConditionSet.__init__(self, equipment.alarm_names)
        self.listeners: list[Listener] = []
        self.powering_down = False
        self.last_error = ""
        self._stop_requested = False
        self._getting_ready: asyncio.Task[None] | None = None
        self._bg = Background()
        self._external_start = False  # a SystemOperation Start is starting its tasks (confirmed starts)
        self.drives_on: bool | None = None  # the controller's drive power, for PowerFeedback equipment
        equipment.add_alarm_listener(self._on_alarm)
        if isinstance(equipment, PowerFeedback):
            equipment.add_power_listener(self._on_power)

    def __repr__(self) -> str:
        return f"<SystemOperation {self.machine.current}>"

    def add_task(self, task: TaskControl) -> None:
        if task not in self.tasks:
            self.tasks.append(task)
            task.system = self

    @property
    def state(self) -> str:
        return self.machine.current

    def machines(self) -> list[StateMachine]:
        return self.machine.walk()

    def _changed(self) -> None:
        _notify(self.listeners)

    # conditions (decision 18)
    def alarm_status(self) -> Status | None:
        """E_ActiveAlarm if a condition is active, E_AcknowledgeRequired if one awaits acknowledging."""
        enabled = [c for c in self.conditions.values() if c.enabled]
        if any(c.active for c in enabled):
            return Status.E_ACTIVE_ALARM
        if any(not c.acked for c in enabled):
            return Status.E_ACKNOWLEDGE_REQUIRED
        return None

    def _on_alarm(self, name: str, active: bool, message: str) -> None:
        self.alarm(name, active, message)

    def acknowledge(self, name: str, comment: str = "") -> None:
        """The condition's Acknowledge; equipment that resets alarms (``AlarmReset``) is told."""
        super().acknowledge(name, comment)
        if isinstance(self.equipment, AlarmReset):
            self.equipment.alarm_acknowledged(name)

    def _on_power(self, on: bool) -> None:
        """The controller's drive power changed (``PowerFeedback``): the power state follows, so that
        SystemOperation is never Ready with the drives off nor Idle/StandBy with them on."""
        self.drives_on = on
        self._follow_power()
        self._changed()  # what a start needs may have changed with it: Executable is evaluated again

    def _follow_power(self) -> None:
        if self.drives_on is None or self.powering_down or self._getting_ready is not None:
            return  # a GetReady or StandDown under way completes the transition itself
        if not self.drives_on and self.machine.current == READY:
            self.last_error = "the controller switched the drives off"
            log.warning("%s", self.last_error)
            self.machine.move(IDLE, Reason.ERROR)
            self.idle.enter(STAND_BY, Reason.ERROR)
            self._changed()
        elif self.drives_on and self.idle.is_in(STAND_BY):
            self.machine.move(READY, Reason.SYSTEM)
            self._changed()

    def conditions_changed(self) -> None:
        self._changed()

    # coupling with task controls (decision 19)
    def allows_task_start(self) -> bool:
        m = self.machine
        return not self.powering_down and (m.current == READY or self.executing.is_in(RUNNING))

    def _task_started(self, task: TaskControl) -> None:
        if self.machine.current == READY:
            self._stop_requested = False
            reason = Reason.EXTERNAL if self._external_start else Reason.SYSTEM
            self.machine.move(EXECUTING, reason)
            self.executing.enter(RUNNING, reason)
            self._changed()

    def _task_stopping(self, reason: Reason = Reason.SYSTEM) -> None:
        # The system is Stopping once every executing task is on its way to a stop.
        if self.executing.is_in(RUNNING) and all(t.stopping for t in self.tasks if t.executing):
            self.executing.move(STOPPING, reason)
            self._changed()

    def _task_finished(self, task: TaskControl, reason: Reason) -> None:
        if self.machine.current != EXECUTING or any(t.executing for t in self.tasks):
            return
        if self._stop_requested:
            reason = Reason.EXTERNAL
        elif reason == Reason.EXTERNAL:  # a task-control Stop: for the system it is a consequence
            reason = Reason.SYSTEM
        self._stop_requested = False
        self.machine.move(READY, reason)
        self._changed()
        self._follow_power()  # the drives went off during the run (a fault): Idle

    def _get_ready_conditions(self) -> Status | None:
        if not self.idle.is_in(STAND_BY) or self.powering_down:
            return Status.E_SYSTEM_STATE
        return self.alarm_status()

    def _stand_down_conditions(self) -> Status | None:
        # In Idle StandDown cancels GettingReady; in Ready it powers down (once).
        if self.idle.is_in(GETTING_READY) or (self.machine.current == READY and not self.powering_down):
            return None
        return Status.E_SYSTEM_STATE

    # methods
    async def get_ready(self) -> int:
        """GetReady: Idle -> (GettingReady) -> Ready once drive power is up. Returns when accepted."""
        if (problem := self._refusal(SYSTEM_OPERATION, "GetReady")) is not None:
            return problem
        self.idle.move(GETTING_READY, Reason.EXTERNAL)
        # Ready follows once the drives are on: the call's completion, the caller's (decision 38).
        self._getting_ready = self._bg.spawn(self._power_up(), context=contextvars.copy_context())
        self._changed()
        return Status.OK

    async def _power_up(self) -> None:
        try:
            await self.equipment.power_up()
        except asyncio.CancelledError:
            raise
        except Exception as e:
            if not isinstance(e, EquipmentError):
                log.exception("power up failed")
            self.last_error = f"getting ready failed: {e}"
            log.warning("%s", self.last_error)
            self._getting_ready = None
            self.idle.move(STAND_BY, Reason.ERROR)
            self.machine.move(IDLE, Reason.ERROR)
            self._changed()
            return
        self._getting_ready = None
        self.machine.move(READY, Reason.EXTERNAL)
        self._changed()

    async def stand_down(self) -> int:
        """StandDown: Ready -> Idle (drive power off), or cancel GettingReady (IdleToIdle)."""
        if (problem := self._refusal(SYSTEM_OPERATION, "StandDown")) is not None:
            return problem
        if self.idle.is_in(GETTING_READY):
            if self._getting_ready is not None:
                self._getting_ready.cancel()
                self._getting_ready = None
            self.idle.move(STAND_BY, Reason.EXTERNAL)
            self.machine.move(IDLE, Reason.EXTERNAL)
            # Until the drives are off again a GetReady would race the power-down: it answers 1.
            self.powering_down = True
            self._bg.spawn(self._power_down(transition=False))
            self._changed()
            return Status.OK
        self.powering_down = True
        # ReadyToIdle follows once the drives are off: the call's completion, the caller's (decision 38).
        self._bg.spawn(self._power_down(transition=True), context=contextvars.copy_context())
        self._changed()
        return Status.OK

    async def _power_down(self, transition: bool) -> None:
        try:
            await self.equipment.power_down()
        except asyncio.CancelledError:
            raise
        except Exception as e:
            if not isinstance(e, EquipmentError):
                log.exception("power down failed")
            self.last_error = f"standing down failed: {e}"
            log.warning("%s", self.last_error)
            self.powering_down = False
            self._changed()
            return
        self.powering_down = False
        if transition and self.machine.current == READY:
            self.machine.move(IDLE, Reason.EXTERNAL)
            self.idle.enter(STAND_BY, Reason.EXTERNAL)
        self._changed()

    def _start_check(self) -> Status | None:
        return self._refusal(SYSTEM_OPERATION, "Start")

    def _start_conditions(self) -> Status | None:
        if self.powering_down:
            return Status.E_SYSTEM_STATE
        alarm = self.alarm_status()
        if alarm is not None:
            return alarm
        problems = [t._start_check() for t in self.tasks if t.machine.current == READY and t.program]
        if not problems:
            return Status.E_SYSTEM_STATE  # nothing to start: the system cannot be Executing without a task
        if all(p is not None for p in problems):
            return problems[0]
        return None

    async def start(self) -> int:
        """Start: starts every task control that is Ready with a program; Ready -> Executing."""
        problem = self._start_check()
        if problem is not None:
            return problem
        if isinstance(self.equipment, ConfirmedStart):
            return await self._start_confirmed()
        self._stop_requested = False
        self.machine.move(EXECUTING, Reason.EXTERNAL)
        self.executing.enter(RUNNING, Reason.EXTERNAL)
        for task in self.tasks:
            if task.machine.current == READY and task._start_check() is None:
                task._start(Reason.SYSTEM)
        self._changed()
        return Status.OK

    async def _start_confirmed(self) -> int:
        """Start each task that can on a controller that confirms starts: ReadyToExecuting (reason 1)
        with the first it confirms; when it confirms none, the first refusal's answer."""
        answers: list[int] = []
        failure: CallError | None = None
        self._external_start = True
        try:
            for task in list(self.tasks):
                if task.machine.current == READY and task._start_check() is None:
                    try:
                        answers.append(await task._start_confirmed(Reason.SYSTEM))
                    except CallError as e:  # Bad_Timeout, Bad_CommunicationError: answered if none started
                        failure = failure or e
        finally:
            self._external_start = False
        if Status.OK in answers:
            return Status.OK
        if failure is not None:
            raise failure
        return answers[0] if answers else Status.E_SYSTEM_STATE

    async def stop(self, stop_mode: int) -> int:
        """Stop: stops every executing task control; ExecutingToReady when all have stopped."""
        mode = _resolve_stop_mode(stop_mode, self.possible_stop_modes, self.default_stop_mode)
        if (problem := self._refusal(SYSTEM_OPERATION, "Stop")) is not None:
            return problem
        self._stop_requested = True
        failed = []
        for task in list(self.tasks):
            if task.executing and not task.stopping:
                # The last task to accept takes RunningToStopping (reason External, see _task_stopping).
                status = await task._stop(mode, Reason.EXTERNAL)
                if status != Status.OK:
                    log.warning("system stop: %s answered %d", task.name, status)
                    failed.append(task.name)
        if failed:
            # A task that keeps running keeps the system Running (no transition leaves Stopping).
            self._stop_requested = False
            self.last_error = f"stop refused by {', '.join(failed)}"
            return Status.E_UNEXPECTED_ERROR
        return Status.OK

    async def close(self) -> None:
        await self._bg.close()


# --- the cell ---------------------------------------------------------------------------------------
class RobotCell:
    """A controller: SystemOperation, its task controls, the equipment and the program library."""

    def __init__(
        self,
        equipment: RobotEquipment,
        library: ProgramLibrary,
        *,
        tables: RoboticsTables,
        task_names: Sequence[str] = ("TaskControl1",),
        motion_devices: Sequence[str] = ("Arm1",),
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
        bounds: ProgramLimits = DEFAULT_LIMITS,
    ) -> None:
        if default_stop_mode not in possible_stop_modes:
            raise ValueError("the default stop mode must be one of the possible stop modes")
        self.equipment = equipment
        self.library = library
        self.system = SystemOperation(
            equipment, tables=tables, possible_stop_modes=possible_stop_modes, default_stop_mode=default_stop_mode
        )
        self.tasks: dict[str, TaskControl] = {
            name: TaskControl(
                name,
                equipment,
                library,
                tables=tables,
                system=self.system,
                motion_devices=motion_devices,
                possible_stop_modes=possible_stop_modes,
                default_stop_mode=default_stop_mode,
                bounds=bounds,
            )
            for name in task_names
        }

    def machines(self) -> list[StateMachine]:
        return self.system.machines() + [m for t in self.tasks.values() for m in t.machines()]

    def add_listener(self, listener: Listener) -> None:
        """Call ``listener`` after any change (state, data, executability) anywhere in the cell."""
        self.system.listeners.append(listener)
        for machine in self.machines():
            machine.listeners.append(lambda _change: listener())

    async def close(self) -> None:
        for task in self.tasks.values():
            await task.close()
        await self.system.close()
