"""Durable PackML Admin data: atomic saves, crashes mid-write, counters across restarts."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from uacell.packml import AdminStore, EquipmentBase, PackMLUnit


class Clock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


def test_round_trip_and_no_temporary_files_left(tmp_path: Path) -> None:
    store = AdminStore(tmp_path / "packml" / "Filler1.json")
    store.save({"a": [1, 2, 3]})
    store.save({"a": [4]})
    assert store.load() == {"a": [4], "version": 1}
    assert [p.name for p in store.path.parent.iterdir()] == ["Filler1.json"]


def test_absent_corrupt_or_foreign_file_gives_defaults(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    store = AdminStore(tmp_path / "admin.json")
    with caplog.at_level(logging.WARNING):
        assert store.load() is None
        store.path.write_text('{"version": 1, "prod_proc')
        assert store.load() is None
        store.path.write_text('[1, 2]')
        assert store.load() is None
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 3
    store.path.write_bytes(b"\xff\xfe garbage")
    unit = PackMLUnit(EquipmentBase(), store=store)  # never a crash
    assert unit.admin.prod_processed_count[0].count == 0


def test_failure_during_write_keeps_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = AdminStore(tmp_path / "admin.json")
    store.save({"n": 1})

    def crash(fd: int) -> None:
        raise KeyboardInterrupt  # the process dies between writing and renaming

    monkeypatch.setattr(os, "fsync", crash)
    with pytest.raises(KeyboardInterrupt):
        store.save({"n": 2})
    monkeypatch.undo()
    assert store.load() == {"n": 1, "version": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["admin.json"]


WRITER = """
import sys
from uacell.packml.admin_store import AdminStore
store = AdminStore(sys.argv[1])
n = 0
print("ready", flush=True)
while True:
    n += 1
    store.save({"n": n, "pad": ["x" * 1000] * 200, "check": n * 7})
"""


def test_killed_writer_leaves_a_complete_file(tmp_path: Path) -> None:
    path = tmp_path / "admin.json"
    AdminStore(path).save({"n": 0, "pad": [], "check": 0})
    for delay in (0.05, 0.15):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE)
        assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        data = json.loads(path.read_text())  # always a whole file, never a torn one
        assert data["check"] == data["n"] * 7


def test_counters_survive_a_restart(tmp_path: Path) -> None:
    clock = Clock()
    store = AdminStore(tmp_path / "Filler1.json")
    unit = PackMLUnit(EquipmentBase(), store=store, clock=clock)
    clock.t += 7.0
    unit.reset_machine()
    unit.state_complete()
    unit.report_production(processed=30, defective=3, consumed=31)
    unit.fault(9, "guard door open")
    unit.close()

    again = PackMLUnit(EquipmentBase(), store=store, clock=clock)
    a = again.admin
    assert (a.prod_processed_count[0].count, a.prod_processed_count[0].acc_count) == (30, 30)
    assert a.prod_defective_count[0].count == 3 and a.prod_consumed_count[0].count == 31
    assert a.state_cumulative_time[1][2] == 7 and a.mode_cumulative_time[1] == 7 and a.acc_time_since_reset == 7
    assert (a.stop_reason.id, a.stop_reason.message) == (9, "guard door open")
    assert [x.id for x in a.alarm_history] == [9] and a.alarm == []
    assert again.states == ("Cleared", "Stopped", None)  # decision 23, whatever state was stored
    again.reset_counters()
    again.close()
    third = PackMLUnit(EquipmentBase(), store=store, clock=clock)
    assert (third.admin.prod_processed_count[0].count, third.admin.prod_processed_count[0].acc_count) == (0, 30)


def test_saves_on_state_change_and_periodically(tmp_path: Path) -> None:
    clock = Clock()
    store = AdminStore(tmp_path / "u.json")
    unit = PackMLUnit(EquipmentBase(), store=store, clock=clock, save_interval=10.0)
    unit.reset_machine()  # a state change saves at once
    assert store.load() is not None
    unit.report_production(processed=5)
    clock.t += 1.0
    unit.tick()
    assert store.load()["prod_processed_count"][0]["count"] == 0  # throttled
    clock.t += 10.0
    unit.tick()
    assert store.load()["prod_processed_count"][0]["count"] == 5


def test_unwritable_store_is_logged_not_raised(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    unit = PackMLUnit(EquipmentBase(), store=AdminStore(blocker / "sub" / "u.json"))
    with caplog.at_level(logging.ERROR):
        unit.reset_machine()
    assert unit.state == "Resetting"
    assert any("cannot save" in r.getMessage() for r in caplog.records)
