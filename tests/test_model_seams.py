"""The named seams around the pure models (docs/architecture.md, "Rules of the house"): the
robotics model reads programs only through
the ``ProgramLibrary`` it is handed (the file reading and its text cache are
``robotics.program_cache``), parsed texts are kept by ``ParsedPrograms``; a PackML unit's publish
bookkeeping (``packml.publishing``) and Admin accounting (``packml.accounting``) work on their own."""

from __future__ import annotations

import ast
import builtins
import inspect
import os
import subprocess
import sys
from datetime import UTC, datetime
from typing import Any

import pytest
from helpers import packml_tables, robotics_tables

import uacell.robotics.loading
import uacell.robotics.model
import uacell.robotics.rules
from uacell.packml.accounting import DURABLE_KEYS, AdminAccounting
from uacell.packml.data import Admin, Status
from uacell.packml.equipment import EquipmentBase
from uacell.packml.model import STOP_COMMAND_IDS, TR88_COMMANDS, PackMLUnit
from uacell.packml.oee import OEE
from uacell.packml.publishing import TIMES_SAVE_PERIOD, Publishing, StoredValues
from uacell.packml.types import PackMLCountDataType
from uacell.robotics.loading import INLINE_PROGRAM_BYTES, KEPT_TEXTS, ParsedPrograms
from uacell.robotics.model import Status as RobotStatus
from uacell.robotics.model import TaskControl
from uacell.robotics.program import DEFAULT_LIMITS
from uacell.robotics.sim import SimulatedRobot


class MemoryLibrary:
    """A ProgramLibrary without files: what a composer may hand the model instead of a directory."""

    def __init__(self, texts: dict[str, str]) -> None:
        self.texts = texts
        self.reads: list[str] = []

    def names(self) -> list[str]:
        return sorted(self.texts)

    def resolve(self, name: str) -> str | None:
        return f"{name}.robot" if name in self.texts else None

    def read(self, relpath: str) -> str:
        self.reads.append(relpath)
        return self.texts[relpath.removesuffix(".robot")]


def test_the_robotics_model_imports_no_asyncua_and_no_file_reading_module() -> None:
    code = "import sys, uacell.robotics.model; print(any(m.startswith('asyncua') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
    for module in (uacell.robotics.model, uacell.robotics.loading, uacell.robotics.rules):
        tree = ast.parse(inspect.getsource(module))
        imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not imported & {"os", "io", "shutil", "pathlib", "uacell.core.files", "uacell.robotics.program_cache"}
        called = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
        assert "open" not in called, module.__name__


async def test_a_task_control_loads_from_the_library_it_is_handed_without_touching_a_file(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    library = MemoryLibrary({"short": "program Short\nmove 5 0 0 0 0 0\nwait 0.1\n"})
    tc = TaskControl("TaskControl1", SimulatedRobot(time_scale=0.001), library, tables=robotics_tables())
    touched: list[object] = []

    def no_files(*args: Any, **kwargs: Any) -> Any:
        touched.append(args[0] if args else None)
        raise AssertionError("the model read a file")

    monkeypatch.setattr(builtins, "open", no_files)
    monkeypatch.setattr(os, "stat", no_files)
    try:
        assert await tc.load_by_name("short") == RobotStatus.OK
        assert await tc.load_by_name("missing") == RobotStatus.NOT_FOUND
    finally:
        monkeypatch.undo()
        await tc.close()
    assert touched == []
    assert library.reads == ["short.robot"]  # no read_small (SmallReads): read in a worker thread
    assert tc.program is not None and tc.program.name == "Short" and tc.program_file == "short.robot"


def test_parsed_programs_keep_small_texts_only_and_the_last_ones() -> None:
    parsed = ParsedPrograms(kept=2)
    text = "program P\nwait 1\n"
    first = parsed.parse(text, (), DEFAULT_LIMITS)
    assert parsed.parse(text, (), DEFAULT_LIMITS) is first  # the same text: the same immutable Program
    assert parsed.parse(text, ((0.0, 1.0),), DEFAULT_LIMITS) is not first  # other axis limits: parsed again
    big = "program Big\n" + "wait 1\n" * (INLINE_PROGRAM_BYTES // 7 + 1)
    assert len(big) > INLINE_PROGRAM_BYTES
    assert parsed.parse(big, (), DEFAULT_LIMITS) is not parsed.parse(big, (), DEFAULT_LIMITS)
    parsed.parse("program Q\nwait 2\n", (), DEFAULT_LIMITS)  # the third small text: the oldest goes
    assert parsed.parse(text, (), DEFAULT_LIMITS) is not first
    assert KEPT_TEXTS == 64


def test_tr88_command_numbers_are_one_table_and_stop_reasons_use_it() -> None:
    assert TR88_COMMANDS == {
        "Reset": 1, "Start": 2, "Stop": 3, "Hold": 4, "Unhold": 5,
        "Suspend": 6, "Unsuspend": 7, "Abort": 8, "Clear": 9, "Complete": 10,
    }  # fmt: skip
    assert STOP_COMMAND_IDS == {"Stop": 3, "Hold": 4, "Suspend": 6, "Abort": 8}
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables())
    unit.abort()
    assert unit.admin.stop_reason.id == TR88_COMMANDS["Abort"]


class _Unit:
    """What Publishing reads (``Published``), with values that can be changed by hand."""

    def __init__(self) -> None:
        self.status = Status(mach_speed=10.0)
        clock = iter(range(1000)).__next__
        self.accounting = AdminAccounting(Admin(), 4, OEE(120.0, 8.0, ()), lambda: float(clock()))
        self.everything: dict[str, Any] = {"Status/MachSpeed": 10.0, "Status/EquipmentBlocked": False}

    def values(self) -> dict[str, Any]:
        return dict(self.everything)

    def oee_values(self) -> dict[str, float | int]:
        return {"OEE": 0.5}


def test_publishing_tells_listeners_only_what_changed_and_only_what_an_operation_named() -> None:
    unit = _Unit()
    told: list[dict[str, Any]] = []
    publishing = Publishing("Filler1")
    publishing.listeners.append(told.append)
    publishing.start(unit.values())
    assert publishing.due  # nothing published yet
    publishing.emit(publishing.select(unit, final=True), final=True)  # every value: none differs
    assert told == [] and not publishing.due
    publishing.change(("Status/MachSpeed",))
    assert publishing.due
    unit.status.mach_speed = unit.everything["Status/MachSpeed"] = 20.0
    unit.everything["Status/EquipmentBlocked"] = True  # not named: not compared
    publishing.emit(publishing.select(unit, final=True), final=True)
    assert told == [{"Status/MachSpeed": 20.0, "Status/StateRequested": 0, "Status/StateChangeInProcess": False,
                     "Status/CurMachSpeed": 0.0}]  # fmt: skip
    assert not publishing.due
    publishing.change()  # anything: every value rebuilt and compared
    publishing.emit(publishing.select(unit, final=True), final=True)
    assert told[1:] == [{"Status/EquipmentBlocked": True}]
    publishing.change()
    publishing.emit(publishing.select(unit, final=True), final=True)
    assert len(told) == 2  # nothing differs: no call


def test_publishing_everything_compares_every_value_even_for_a_named_change() -> None:
    unit = _Unit()
    told: list[dict[str, Any]] = []
    publishing = Publishing("Filler1")
    publishing.everything = True
    publishing.listeners.append(told.append)
    publishing.start(unit.values())
    publishing.emit(publishing.select(unit, final=True), final=True)
    publishing.change(("Status/MachSpeed",))
    unit.everything["Status/EquipmentBlocked"] = True
    publishing.emit(publishing.select(unit, final=True), final=True)
    assert told == [{"Status/EquipmentBlocked": True}]


class _Store:
    path = "admin.json"

    def __init__(self) -> None:
        self.submitted: list[dict[str, Any]] = []

    def submit(self, data: dict[str, Any], done: Any) -> None:
        self.submitted.append(data)
        done(None)


def test_stored_values_save_counts_at_once_and_times_alone_once_a_period() -> None:
    now = [0.0]
    store = _Store()
    saving = StoredValues("Filler1", store, lambda: now[0])  # type: ignore[arg-type]
    first = dict.fromkeys(DURABLE_KEYS, 0) | {"Admin/ProdProcessedCount": [1]}
    saving.start(first)
    done: list[dict[str, Any]] = []

    def answered(d: dict[str, Any], e: OSError | None) -> None:
        done.append(d)
        saving.stored(d, e)

    def save(durable: dict[str, Any]) -> None:
        saving.submit(durable, lambda: {"n": len(store.submitted)}, answered)

    times = {**first, "Admin/AccTimeSinceReset": 1}
    now[0] = TIMES_SAVE_PERIOD / 2
    values = dict(times)
    saving.settle(values, lambda: save(times))
    assert store.submitted == [] and saving.times_due  # only time passed, within the period: later
    assert values["Admin/AccTimeSinceReset"] == 0  # clients see what is stored
    assert not saving.save_due(10.0)
    now[0] = TIMES_SAVE_PERIOD
    assert saving.save_due(10.0)
    counted = {**times, "Admin/ProdProcessedCount": [2]}
    values = dict(counted)
    saving.settle(values, lambda: save(counted))
    assert store.submitted == [{"n": 0}] and done == [counted] and not saving.times_due
    assert values == counted and not saving.storing


def test_admin_accounting_rebuilds_times_at_whole_seconds_and_resets_counts_but_not_acc_counts() -> None:
    now = [0.0]
    admin = Admin(
        prod_processed_count=[PackMLCountDataType(1, "Product", count=5, acc_count=7)],
        prod_consumed_count=[PackMLCountDataType(100, "Material")],
    )
    accounting = AdminAccounting(admin, 4, OEE(120.0, 8.0, ()), lambda: now[0])
    assert accounting.account(1, 6, "Execute")  # first: the times are built
    now[0] = 0.5
    assert not accounting.account(1, 6, "Execute")  # no whole second passed
    now[0] = 1.2
    assert accounting.account(1, 6, "Execute")
    assert admin.mode_cumulative_time[1] == 1 and admin.state_current_time[1][6] == 1
    assert admin.acc_time_since_reset == 1
    accounting.produce(2, 0, 0)
    assert (admin.prod_processed_count[0].count, admin.prod_processed_count[0].acc_count) == (7, 9)
    stored = accounting.to_json("Filler1", datetime(2026, 11, 27, tzinfo=UTC).isoformat())
    accounting.reset()
    assert accounting.account(1, 6, "Execute")
    assert admin.acc_time_since_reset == 0 and admin.prod_processed_count[0].count == 0
    assert admin.prod_processed_count[0].acc_count == 9
    accounting.load(stored)
    assert accounting.acc == pytest.approx(1.2) and admin.prod_processed_count[0].count == 7
