"""TaskControl's program loading (OPC 40010-1 LoadByName, LoadByNodeId, UnloadProgram, UnloadByName,
UnloadByNodeId; docs/decisions.md 11-15, 70), free of OPC UA and of files.

Programs come from a ``ProgramLibrary`` handed in by whoever composes the cell (the binder gives a
``uacell.robotics.program_cache.DirectoryLibrary`` over the Controller's Programs folder): this module
reads no file itself. Texts it has parsed are kept in ``ParsedPrograms`` (a Program is immutable).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from uacell.core.capabilities import has
from uacell.core.errors import CallError
from uacell.core.fsm import Reason, StateMachine
from uacell.robotics.equipment import (
    EquipmentError,
    ProgramCatalogue,
    ProgramRejected,
    RobotEquipment,
    UnknownProgram,
)
from uacell.robotics.program import Kind, Program, ProgramError, ProgramLimits, measure, parse
from uacell.robotics.rules import (
    AT_PROGRAM_START,
    EXECUTING,
    IDLE,
    READY,
    SUSPENDED,
    TASK_CONTROL,
    Guarded,
    Status,
    TaskModule,
)

log = logging.getLogger(__name__)


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


@runtime_checkable
class SmallReads(Protocol):
    """A ``ProgramLibrary`` that can read a small file cheaply, on the event loop."""

    def read_small(self, relpath: str) -> str | None:
        """The text of a file of at most INLINE_PROGRAM_BYTES; None for a larger one, or one whose size
        cannot be known (``read`` then says why)."""
        ...


# Programs up to this size are read and checked on the event loop (about 70 us a KiB here); larger
# ones in a worker thread, so that a big file never holds up other clients' requests.
INLINE_PROGRAM_BYTES = 4096
KEPT_TEXTS = 64  # the small texts a library keeps (``DirectoryLibrary.read``), the programs ``ParsedPrograms`` keeps


class LoadFailure(Exception):
    """A load that fails with ``status`` (the reason is the message)."""

    def __init__(self, status: Status, reason: str) -> None:
        super().__init__(reason)
        self.status = status


class ParsedPrograms:
    """The programs parsed from small texts (at most INLINE_PROGRAM_BYTES), by text, axis limits and
    bounds, the last KEPT_TEXTS: loading the same program again costs a look-up, not a parse. A
    Program is immutable: the same text gives the same one."""

    def __init__(self, kept: int = KEPT_TEXTS) -> None:
        self._kept = kept
        self._programs: dict[tuple[str, tuple[tuple[float, float], ...], ProgramLimits], Program] = {}

    def parse(self, text: str, limits: tuple[tuple[float, float], ...], bounds: ProgramLimits) -> Program:
        key = (text, limits, bounds)
        program = self._programs.get(key)
        if program is None:
            program = parse(text, limits, bounds=bounds)
            if len(text) <= INLINE_PROGRAM_BYTES:
                if len(self._programs) >= self._kept:
                    self._programs.pop(next(iter(self._programs)), None)  # the oldest
                self._programs[key] = program
        return program


class ProgramLoading(Guarded):
    """What a TaskControl does to load and unload programs and modules: from its ``library`` (a file
    in Programs: uacell holds the text) or the controller's own (a ``ProgramCatalogue``)."""

    name: str
    equipment: RobotEquipment
    library: ProgramLibrary
    bounds: ProgramLimits
    motion_devices: tuple[str, ...]
    machine: StateMachine
    ready: StateMachine
    program: Program | None
    program_file: str | None
    on_controller: bool
    pointer: int
    current_line: int
    last_error: str
    _lock: asyncio.Lock
    _modules: dict[str, tuple[Program, str | None]]
    _parsed: ParsedPrograms

    if TYPE_CHECKING:  # TaskControl's

        def _changed(self) -> None: ...

    @property
    def modules(self) -> list[TaskModule]:
        used: set[str] = set(self.program.uses) if self.program else set()
        for module, _ in self._modules.values():
            used.update(module.uses)
        return [TaskModule(m.name, m.version, m.name in used, rel) for m, rel in self._modules.values()]

    def _something_loaded(self) -> Status | None:
        return Status.E_SYSTEM_STATE if self.program is None and not self._modules else None

    async def load_by_name(self, name: str) -> int:
        """LoadByName: a program or module from the library by file name (without extension)."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "LoadByName")) is not None:
                return problem
            relpath = self.library.resolve(name)
            if relpath is not None:  # a file in Programs: uacell holds the text (also on a gateway robot)
                return await self._load(relpath)
            catalogue = self.equipment if has(self.equipment, ProgramCatalogue) else None
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
            raise LoadFailure(Status.NOT_FOUND, f"no file {relpath!r}") from None
        except ProgramError as e:
            raise LoadFailure(Status.INVALID_CONTENT, f"{relpath}: {e}") from e
        except UnicodeDecodeError as e:
            raise LoadFailure(
                Status.INVALID_CONTENT, f"{relpath}: not UTF-8 text ({e.reason} at byte {e.start})"
            ) from e
        except OSError as e:
            raise LoadFailure(Status.E_UNEXPECTED_ERROR, f"cannot read {relpath!r}: {e}") from e
        try:
            # No motion device (motion_device = ""): nothing to move, a 'move' is refused (decision 33).
            limits = tuple(a.limits for a in self.equipment.axes) if self.motion_devices else ()
            program = self._parsed.parse(text, limits, self.bounds)
            # What can be known before Start: the file alone (and the modules loaded now) is within bounds.
            measure(program, modules, self.bounds, partial=True)
        except ProgramError as e:
            raise LoadFailure(Status.INVALID_CONTENT, f"{relpath}: {e}") from e
        return program

    async def _load(self, relpath: str) -> int:
        try:
            modules = {n: m for n, (m, _) in self._modules.items()}
            # ``read_small`` is optional for a library (``SmallReads``; DirectoryLibrary has it): a small
            # file is read and checked on the loop (a few hundred microseconds at most), anything else
            # in a thread.
            small = self.library.read_small if has(self.library, SmallReads) else None
            program = self._read_and_check(relpath, modules, small) if small is not None else None
            if program is None:
                program = await asyncio.to_thread(self._read_and_check, relpath, modules)
            assert program is not None  # read by the library's ``read``: a text or an error
            if program.kind is Kind.MODULE and self.program is not None and program.name == self.program.name:
                raise LoadFailure(Status.INVALID_CONTENT, f"module {program.name} has the program's name")
            if program.kind is Kind.PROGRAM and program.name in self._modules:
                raise LoadFailure(Status.INVALID_CONTENT, f"program {program.name} has a loaded module's name")
            try:
                await self.equipment.load(self.name, program)
            except ProgramRejected as e:
                raise LoadFailure(Status.INVALID_CONTENT, f"controller rejected {relpath}: {e}") from e
            except EquipmentError as e:
                raise LoadFailure(Status.E_UNEXPECTED_ERROR, f"controller could not load {relpath}: {e}") from e
        except LoadFailure as f:
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

    async def load_controller_program(self, name: str) -> int:
        """LoadByNodeId, after the binding resolved the NodeId to a program the controller holds."""
        async with self._lock:
            if (problem := self._refusal(TASK_CONTROL, "LoadByNodeId")) is not None:
                return problem
            return await self._select(name)

    async def _select(self, name: str) -> int:
        """Select the controller's own program ``name`` (a ``ProgramCatalogue``): no file, no text;
        what it calls is the controller's business (Start never answers -3 for it)."""
        assert has(self.equipment, ProgramCatalogue)
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
