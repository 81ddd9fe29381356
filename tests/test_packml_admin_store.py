"""Durable PackML Admin data: atomic saves, crashes mid-write, counters across restarts."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import FakeClock, packml_tables, raw_call

from uacell.packml import AdminStore, EquipmentBase, PackMLUnit


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
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store)  # never a crash
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
    clock = FakeClock(50.0)
    store = AdminStore(tmp_path / "Filler1.json")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    clock.now += 7.0
    unit.reset_machine()
    unit.state_complete()
    unit.report_production(processed=30, defective=3, consumed=31)
    unit.fault(9, "guard door open")
    unit.close()

    again = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    a = again.admin
    assert (a.prod_processed_count[0].count, a.prod_processed_count[0].acc_count) == (30, 30)
    assert a.prod_defective_count[0].count == 3 and a.prod_consumed_count[0].count == 31
    assert a.state_cumulative_time[1][2] == 7 and a.mode_cumulative_time[1] == 7 and a.acc_time_since_reset == 7
    assert (a.stop_reason.id, a.stop_reason.message) == (9, "guard door open")
    assert [x.id for x in a.alarm_history] == [9] and a.alarm == []
    assert again.states == ("Cleared", "Stopped", None)  # decision 23, whatever state was stored
    again.reset_counters()
    again.close()
    third = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    assert (third.admin.prod_processed_count[0].count, third.admin.prod_processed_count[0].acc_count) == (0, 30)


def test_saves_on_state_change_and_before_publishing(tmp_path: Path) -> None:
    clock = FakeClock(50.0)
    store = AdminStore(tmp_path / "u.json")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock, save_interval=10.0)
    unit.reset_machine()  # a state change saves at once
    assert store.load() is not None
    unit.report_production(processed=5)
    assert store.load()["prod_processed_count"][0]["count"] == 5  # stored before clients could see it
    clock.now += 10.0
    unit.tick()
    assert store.load()["acc_time_since_reset"] == 10.0


def test_nothing_is_published_before_it_is_stored(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Decision 28: a crash right after a client read a value never loses it, yet time alone does not make
    the unit write ten times a second."""
    clock = FakeClock(50.0)
    store = AdminStore(tmp_path / "u.json")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    saves: list[int] = []
    real_save = store.save
    monkeypatch.setattr(store, "save", lambda data: (saves.append(1), real_save(data)))

    def check(changed: dict) -> None:
        stored = store.load()
        assert stored is not None
        for key, field in (("Admin/ProdProcessedCount", "prod_processed_count"),
                           ("Admin/ProdDefectiveCount", "prod_defective_count"),
                           ("Admin/ProdConsumedCount", "prod_consumed_count")):
            for c in changed.get(key, []):
                (s,) = [x for x in stored[field] if x["id"] == c.id]
                assert (s["count"], s["acc_count"]) == (c.count, c.acc_count)
        if "Admin/AccTimeSinceReset" in changed:
            assert stored["acc_time_since_reset"] >= changed["Admin/AccTimeSinceReset"]
        for mode, row in enumerate(changed.get("Admin/StateCumulativeTime", [])):
            for state, t in enumerate(row):
                assert stored["state_cumulative_time"][mode][state] >= t

    unit.listeners.append(check)
    unit.reset_machine()
    unit.state_complete()
    unit.start([])
    unit.state_complete()
    saves.clear()
    for i in range(100):  # 10 s of ticks, producing now and then
        clock.now += 0.1
        if i % 7 == 0:
            unit.report_production(processed=1, consumed=1)
        unit.tick()
    assert unit.admin.prod_processed_count[0].count == 15
    # one save per visible change (a package, a whole second of the times), far fewer than the 100 ticks
    assert 15 <= len(saves) <= 15 + 3 * 11


def test_unwritable_store_is_logged_not_raised(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=AdminStore(blocker / "sub" / "u.json"))
    with caplog.at_level(logging.ERROR):
        unit.reset_machine()
        unit.state_complete()
        unit.report_production(processed=3)
    assert unit.state == "Idle"
    assert [r.getMessage() for r in caplog.records].count(
        f"Filler1: cannot save PackML admin data to {blocker / 'sub' / 'u.json'}") == 1  # once, not per change


async def test_kill_9_during_production_loses_nothing_a_client_read(tmp_path: Path) -> None:
    """A real `uacell serve` is killed (SIGKILL) while Filler1 produces; after a restart every Admin
    counter and time is at least what a client read just before the kill."""
    from asyncua import Client, ua
    from conftest import start_serve

    config = tmp_path / "uacell.toml"
    config.write_text("[packml]\nacting_time = 0.05\nmach_speed = 600.0\n")
    data = tmp_path / "data"
    cell, pml_uri = "urn:uacell:cell", "http://opcfoundation.org/UA/PackML/"
    machine = "Filler1.BaseStateMachine.MachineState"
    watched = ("ProdProcessedCount", "ProdDefectiveCount", "ProdConsumedCount")

    async def read_admin(client: Client, ns: int) -> tuple[list[tuple[int, int]], int, int]:
        counts = []
        for name in watched:
            (c,) = await client.get_node(ua.NodeId(f"Filler1.Admin.{name}", ns)).read_value()
            counts.append((c.Count, c.AccCount))
        acc = await client.get_node(ua.NodeId("Filler1.Admin.AccTimeSinceReset", ns)).read_value()
        cum = await client.get_node(ua.NodeId("Filler1.Admin.StateCumulativeTime", ns)).read_value()
        return counts, acc, cum[1][6]  # Produce row, Execute column

    async def call(client: Client, ns: int, obj: str, method: str, *args: ua.Variant) -> None:
        res = await raw_call(client, ua.NodeId(obj, ns), ua.NodeId(f"{obj}.{method}", ns), *args)
        assert res.StatusCode.is_good(), (method, res.StatusCode)

    async def execute_state(client: Client, ns: int) -> str | None:
        node = client.get_node(ua.NodeId(f"{machine}.ExecuteState.CurrentState", ns))
        dv = await node.read_data_value(raise_on_bad_status=False)
        return dv.Value.Value.Text if dv.StatusCode.is_good() else None

    sp = start_serve(data, "--config", str(config))
    try:
        async with Client(sp.endpoint, timeout=30) as client:
            await client.load_data_type_definitions()
            ns = await client.get_namespace_index(cell)
            assert await client.get_namespace_index(pml_uri) > 0
            await call(client, ns, machine, "Reset")
            deadline = time.monotonic() + 20
            while await execute_state(client, ns) != "Idle":
                assert time.monotonic() < deadline
                await asyncio.sleep(0.05)
            empty = ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)
            await call(client, ns, f"{machine}.ExecuteState", "Start", empty)
            last = await read_admin(client, ns)
            deadline = time.monotonic() + 20
            # keep reading while it produces (10 packages/s); kill right after a read
            while last[0][0][0] < 12 or last[2] < 1:
                assert time.monotonic() < deadline, last
                await asyncio.sleep(0.03)
                last = await read_admin(client, ns)
            sp.proc.send_signal(signal.SIGKILL)
            sp.proc.wait(30)
    finally:
        sp.stop()
    assert sp.proc.returncode == -signal.SIGKILL

    sp = start_serve(data, "--config", str(config))
    try:
        async with Client(sp.endpoint, timeout=30) as client:
            await client.load_data_type_definitions()
            ns = await client.get_namespace_index(cell)
            counts, acc, execute_time = await read_admin(client, ns)
    finally:
        sp.stop()
    for name, now, before in zip(watched, counts, last[0], strict=True):
        assert now[0] >= before[0] and now[1] >= before[1], (name, now, before)
    assert counts[0][0] >= 12 and acc >= last[1] and execute_time >= last[2] >= 1
