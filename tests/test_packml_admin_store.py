"""Durable PackML Admin data: atomic saves, crashes mid-write, counters across restarts."""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from helpers import FakeClock, packml_tables, raw_call

from uacell.packml import AdminStore, EquipmentBase, PackMLUnit, admin_store
from uacell.packml.admin_store import BATCH, AdminWriter, Journal


def saved(store: AdminStore) -> dict[str, Any]:
    """What ``store`` holds, where a test has saved to it."""
    data = store.load()
    assert data is not None
    return data


def test_round_trip_and_no_temporary_files_left(tmp_path: Path) -> None:
    store = AdminStore(tmp_path / "packml" / "Filler1.json")
    store.save({"a": [1, 2, 3]})
    store.save({"a": [4]})
    assert store.load() == {"a": [4], "version": 1}
    assert [p.name for p in store.path.parent.iterdir()] == ["Filler1.json"]


def test_a_removed_directory_is_made_again_at_the_next_save(tmp_path: Path) -> None:
    """The directory is made by the first save, and again by the next save after somebody removed it
    (it is not made, or looked for, before every save)."""
    store = AdminStore(tmp_path / "data" / "packml" / "Filler1.json")
    assert not store.path.parent.exists()
    store.save({"a": [1]})
    (store.path).unlink()
    store.path.parent.rmdir()
    (tmp_path / "data").rmdir()
    store.save({"a": [2]})
    assert store.load() == {"a": [2], "version": 1}
    assert [p.name for p in store.path.parent.iterdir()] == ["Filler1.json"]


def test_leftover_temporaries_of_a_crashed_save_are_removed_at_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    store = AdminStore(tmp_path / "packml" / "Filler1.json")
    store.save({"a": [1]})
    folder = store.path.parent
    (folder / "Filler1.json.k3j_x9.tmp").write_text('{"version": 1, "a"')  # a save killed before its rename
    (folder / "Filler1.json.q81.tmp").write_text("")
    (folder / "Capper.json.z7.tmp").write_text("")  # another unit's: its own store cleans it
    with caplog.at_level(logging.INFO):
        assert store.load() == {"a": [1], "version": 1}
    assert sorted(p.name for p in folder.iterdir()) == ["Capper.json.z7.tmp", "Filler1.json"]
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.WARNING, f"removed 2 leftover temporary file(s) of {store.path} (a save interrupted by a crash)")
    ]


def test_absent_corrupt_or_foreign_file_gives_defaults(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    store = AdminStore(tmp_path / "admin.json")
    with caplog.at_level(logging.INFO):
        assert store.load() is None  # a first start: no file yet is normal, not a warning
        assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
            (logging.INFO, f"no PackML admin data at {store.path} yet (a first start); starting from defaults")
        ]
        caplog.clear()
        store.path.write_text('{"version": 1, "prod_proc')
        assert store.load() is None
        store.path.write_text("[1, 2]")
        assert store.load() is None
    assert [r.levelno for r in caplog.records] == [logging.WARNING, logging.WARNING]  # damage warns
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
    assert saved(store)["prod_processed_count"][0]["count"] == 5  # stored before clients could see it
    clock.now += 10.0
    unit.tick()
    assert saved(store)["acc_time_since_reset"] == 10.0


def test_nothing_is_published_before_it_is_stored(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Decision 28: a crash right after a client read a value never loses it, yet time alone does not make
    the unit write ten times a second."""
    clock = FakeClock(50.0)
    store = AdminStore(tmp_path / "u.json")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    saves: list[int] = []
    real_save = store.save

    def counted_save(data: dict[str, Any]) -> None:
        saves.append(1)
        real_save(data)

    monkeypatch.setattr(store, "save", counted_save)

    def check(changed: dict[str, Any]) -> None:
        stored = store.load()
        assert stored is not None
        for key, field in (
            ("Admin/ProdProcessedCount", "prod_processed_count"),
            ("Admin/ProdDefectiveCount", "prod_defective_count"),
            ("Admin/ProdConsumedCount", "prod_consumed_count"),
        ):
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


def test_time_alone_is_stored_and_published_once_a_second(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stored times pass their whole seconds at different instants; time alone makes one save (and one
    publication of the stored times) a second, a package is stored at once."""
    clock = FakeClock(50.0)
    store = AdminStore(tmp_path / "u.json")
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    clock.now += 0.55
    unit.tick()
    unit.reset_machine()
    unit.state_complete()  # Idle: its seconds and the unit's now fall at different instants
    saves: list[float] = []
    real_save = store.save

    def timed_save(data: dict[str, Any]) -> None:
        saves.append(clock.now)
        real_save(data)

    monkeypatch.setattr(store, "save", timed_save)
    published: list[tuple[float, int]] = []
    unit.listeners.append(
        lambda changed: published.extend((clock.now, v) for k, v in changed.items() if k == "Admin/AccTimeSinceReset")
    )
    for _ in range(100):  # 10 s
        clock.now += 0.1
        unit.tick()
    assert 9 <= len(saves) <= 11
    assert all(b - a >= 1.0 - 1e-6 for a, b in itertools.pairwise(saves))
    assert [v for _, v in published] == list(range(1, len(published) + 1)) and len(published) >= 9
    assert all(v <= t - 50.0 < v + 2.0 for t, v in published)  # at most a second late
    saves.clear()
    unit.report_production(processed=1)  # not a time: stored at once
    assert len(saves) == 1 and saved(store)["prod_processed_count"][0]["count"] == 1


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
        f"Filler1: cannot save PackML admin data to {blocker / 'sub' / 'u.json'}"
    ) == 1  # once, not per change


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
        async with Client(sp.endpoint, timeout=30, watchdog_intervall=30.0) as client:
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
        async with Client(sp.endpoint, timeout=30, watchdog_intervall=30.0) as client:
            await client.load_data_type_definitions()
            ns = await client.get_namespace_index(cell)
            counts, acc, execute_time = await read_admin(client, ns)
    finally:
        sp.stop()
    for name, now, before in zip(watched, counts, last[0], strict=True):
        assert now[0] >= before[0] and now[1] >= before[1], (name, now, before)
    assert counts[0][0] >= 12 and acc >= last[1] and execute_time >= last[2] >= 1


# --- one writer thread for every unit's store -------------------------------------------------------


class SlowDisk:
    """Stands in for a slow disk under the writer's journal (``Journal.append``): each append waits until
    ``release()``d and records which thread wrote what, one entry per store."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.gate = threading.Event()
        self.started = threading.Event()
        self.writes: list[tuple[str, dict[str, Any]]] = []
        self.threads: set[int] = set()
        real = Journal.append

        def append(journal: Journal, entries: list[tuple[AdminStore, dict[str, Any]]]) -> None:
            self.threads.add(threading.get_ident())
            self.started.set()
            assert self.gate.wait(30), "the test never released the slow disk"
            real(journal, entries)
            self.writes.extend(
                (store.path.name, {k: v for k, v in data.items() if k != "seq"}) for store, data in entries
            )

        monkeypatch.setattr(Journal, "append", append)

    def release(self) -> None:
        self.gate.set()


async def test_saves_run_off_the_loop_and_values_are_published_once_durable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = SlowDisk(monkeypatch)
    writer = AdminWriter(asyncio.get_running_loop())
    store = AdminStore(tmp_path / "Filler1.json", writer)
    clock = FakeClock(50.0)
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=clock)
    published: list[dict[str, Any]] = []

    def seen(changed: dict[str, Any]) -> None:
        if "Admin/ProdProcessedCount" in changed:
            stored = AdminStore(store.path).load()  # what a restart after a crash right now would read
            assert (
                stored is not None
                and stored["prod_processed_count"][0]["count"] == changed["Admin/ProdProcessedCount"][0].count
            )
        published.append(changed)

    unit.listeners.append(seen)
    try:
        unit.report_production(processed=5)
        # The write blocks on the slow disk, yet the loop runs on: the save is not on it.
        await asyncio.to_thread(disk.started.wait, 30)
        for _ in range(3):
            await asyncio.sleep(0)
        assert unit.admin.prod_processed_count[0].count == 5
        assert not any("Admin/ProdProcessedCount" in c for c in published)  # not durable yet: not shown
        assert not store.path.exists()
        assert unit.storing  # a call that did this would wait
        disk.release()
        await store.stored()
        assert not unit.storing
        assert disk.threads and threading.get_ident() not in disk.threads
        counts = [c["Admin/ProdProcessedCount"][0].count for c in published if "Admin/ProdProcessedCount" in c]
        assert counts == [5]
    finally:
        disk.release()
        await writer.close()
    assert writer._thread.is_alive() is False


async def test_a_store_changed_while_queued_is_written_once_with_the_newest_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = SlowDisk(monkeypatch)
    writer = AdminWriter(asyncio.get_running_loop())
    a, b = AdminStore(tmp_path / "a.json", writer), AdminStore(tmp_path / "b.json", writer)
    done: list[tuple[str, int, OSError | None]] = []

    def submit(store: AdminStore, n: int) -> None:
        store.submit({"n": n}, lambda error: done.append((store.path.name, n, error)))

    try:
        submit(a, 1)
        await asyncio.to_thread(disk.started.wait, 30)  # a=1 is being written: the rest queues
        for n in (2, 3, 4):
            submit(a, n)
        submit(b, 1)
        submit(a, 5)
        disk.release()
        await writer.flush()
    finally:
        disk.release()
        await writer.close()
    assert [(name, data["n"]) for name, data in disk.writes] == [("a.json", 1), ("a.json", 5), ("b.json", 1)]
    assert done == [("a.json", 1, None), ("a.json", 5, None), ("b.json", 1, None)]  # superseded data is not told
    assert a.load() == {"n": 5, "version": 1} and b.load() == {"n": 1, "version": 1}


async def test_a_store_somebody_waits_for_is_written_next(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    disk = SlowDisk(monkeypatch)
    writer = AdminWriter(asyncio.get_running_loop())
    stores = [AdminStore(tmp_path / f"u{i:02}.json", writer) for i in range(3 * BATCH)]
    try:
        stores[0].submit({"n": 0}, lambda error: None)
        await asyncio.to_thread(disk.started.wait, 30)
        for store in stores[1:]:
            store.submit({"n": 0}, lambda error: None)
        waited = asyncio.ensure_future(stores[-1].stored())
        await asyncio.sleep(0)
        disk.release()
        await waited
        written = [name for name, _ in disk.writes]
        assert written.index(stores[-1].path.name) == 1  # the batch after the first, at its head
        await writer.flush()
    finally:
        disk.release()
        await writer.close()
    assert sorted(name for name, _ in disk.writes) == sorted(s.path.name for s in stores)  # each once


async def test_a_unit_producing_on_a_slow_disk_publishes_the_newest_stored_count(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = SlowDisk(monkeypatch)
    writer = AdminWriter(asyncio.get_running_loop())
    store = AdminStore(tmp_path / "Filler1.json", writer)
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=store, clock=FakeClock(50.0))
    published: list[int] = []
    unit.listeners.append(
        lambda changed: published.extend(c[0].count for k, c in changed.items() if k == "Admin/ProdProcessedCount")
    )
    try:
        unit.report_production(processed=1)
        await asyncio.to_thread(disk.started.wait, 30)
        for _ in range(10):  # ten more packages while the first is written: one more write
            unit.report_production(processed=1)
        disk.release()
        await store.stored()
    finally:
        disk.release()
        await writer.close()
    assert [data["prod_processed_count"][0]["count"] for _, data in disk.writes] == [1, 11]
    assert published == [1, 11]


async def test_a_failing_store_is_logged_once_and_does_not_stop_the_writer(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    writer = AdminWriter(asyncio.get_running_loop())
    bad = AdminStore(blocker / "sub" / "u.json", writer)
    good = AdminStore(tmp_path / "good.json", writer)
    unit = PackMLUnit(EquipmentBase(), tables=packml_tables(), store=bad)
    published: list[int] = []
    unit.listeners.append(
        lambda changed: published.extend(c[0].count for k, c in changed.items() if k == "Admin/ProdProcessedCount")
    )
    try:
        with caplog.at_level(logging.ERROR):
            for n in (1, 2):
                unit.report_production(processed=1)
                await bad.stored()
                assert published[-1:] == [n]  # a failing disk does not freeze what clients see
        good.submit({"n": 1}, lambda error: None)
        await writer.flush()
    finally:
        await writer.close()
    assert good.load() == {"n": 1, "version": 1}
    assert [r.getMessage() for r in caplog.records].count(f"Filler1: cannot save PackML admin data to {bad.path}") == 1


WRITER_THREAD = """
import asyncio, sys
from pathlib import Path
from typing import Any
from uacell.packml.admin_store import AdminStore, AdminWriter

async def main() -> None:
    writer = AdminWriter(asyncio.get_running_loop())
    stores = [AdminStore(Path(sys.argv[1]) / f"u{i}.json", writer) for i in range(4)]
    n = 0
    print("ready", flush=True)
    while True:
        n += 1
        for i, store in enumerate(stores):
            store.submit({"n": n, "pad": ["x" * 1000] * 50, "check": n * 7},
                         lambda error, i=i, n=n: print(f"stored {i} {n}", flush=True))
        await asyncio.sleep(0.002)

asyncio.run(main())
"""


def test_killed_writer_thread_keeps_every_store_at_least_as_told(tmp_path: Path) -> None:
    """The writer thread killed (SIGKILL) at any moment: every file is whole, and holds at least the data
    the writer had reported durable (what clients could have read)."""
    proc = subprocess.Popen([sys.executable, "-c", WRITER_THREAD, str(tmp_path)], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
    told = dict.fromkeys(range(4), 0)
    deadline = time.monotonic() + 60
    try:
        while min(told.values()) < 20:  # some stored batches, then a kill right after a report
            assert time.monotonic() < deadline, told
            _, unit_no, count = proc.stdout.readline().split()
            told[int(unit_no)] = int(count)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    proc.stdout.close()
    for i, n in told.items():
        data = AdminStore(tmp_path / f"u{i}.json").load()  # the file, or its newer line in the journal
        assert data is not None and data["check"] == data["n"] * 7 and data["n"] >= n, (i, data, n)


# --- the writer's journal --------------------------------------------------------------------------


def _on_file(path: Path) -> dict[str, Any] | None:
    """The unit's own file as it is on disk (without the journal)."""
    return json.loads(path.read_text()) if path.exists() else None


def _journal_lines(directory: Path) -> list[dict[str, Any]]:
    path = directory / "journal.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


async def _stored(store: AdminStore, data: dict[str, Any]) -> None:
    told: asyncio.Future[OSError | None] = asyncio.get_running_loop().create_future()
    store.submit(data, lambda error: told.set_result(error))
    assert await asyncio.wait_for(told, 10) is None


async def test_the_writer_appends_to_the_journal_and_folds_it_into_the_files_when_it_closes(tmp_path: Path) -> None:
    AdminStore(tmp_path / "a.json").save({"n": 0})  # a unit's file from an earlier run
    writer = AdminWriter(asyncio.get_running_loop())
    a, b = AdminStore(tmp_path / "a.json", writer), AdminStore(tmp_path / "b.json", writer)
    assert a.load() == {"n": 0, "version": 1}
    try:
        for n in (1, 2):
            await _stored(a, {"n": n})
        await _stored(b, {"n": 1})
        # durable in the journal, one line per save; the files are as they were
        lines = _journal_lines(tmp_path)
        assert [(x["unit"], x["data"]["n"], x["data"]["seq"]) for x in lines] == [
            ("a.json", 1, 2),
            ("a.json", 2, 3),
            ("b.json", 1, 1),
        ]
        assert (
            _on_file(tmp_path / "a.json") == {"n": 0, "seq": 1, "version": 1} and _on_file(tmp_path / "b.json") is None
        )
        assert (tmp_path / "journal.jsonl").stat().st_mode & 0o777 == 0o600  # as the units' files
        # what a restart right now reads: the newer of the file and the journal
        assert AdminStore(tmp_path / "a.json").load() == {"n": 2, "version": 1}
        assert AdminStore(tmp_path / "b.json").load() == {"n": 1, "version": 1}
    finally:
        await writer.close()
    assert _journal_lines(tmp_path) == []  # folded: a clean restart reads the units' files alone
    assert _on_file(tmp_path / "a.json") == {"n": 2, "seq": 3, "version": 1}
    assert _on_file(tmp_path / "b.json") == {"n": 1, "seq": 1, "version": 1}
    late = AdminStore(tmp_path / "a.json")  # after the writer closed a save goes to the file at once
    assert late.load() == {"n": 2, "version": 1} and late.seq == 3


async def test_a_journal_past_its_limit_is_folded_and_loads_never_see_older_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(admin_store, "JOURNAL_LIMIT", 2_000)
    writer = AdminWriter(asyncio.get_running_loop())
    stores = [AdminStore(tmp_path / f"u{i}.json", writer) for i in range(3)]
    try:
        for n in range(1, 30):
            for store in stores:
                await _stored(store, {"n": n, "pad": "x" * 100})
            for i in range(3):
                assert AdminStore(tmp_path / f"u{i}.json").load()["n"] == n  # type: ignore[index]
        assert (tmp_path / "journal.jsonl").stat().st_size <= 2_000 + 3 * 300  # folded again and again
        assert _on_file(tmp_path / "u0.json")["n"] > 1  # type: ignore[index]  # folds wrote the files
    finally:
        await writer.close()


async def test_a_journal_a_crash_left_is_read_then_folded_before_the_next_run_appends(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    AdminStore(tmp_path / "a.json").save({"n": 1})
    AdminStore(tmp_path / "b.json").save({"n": 1})
    whole = [
        {"unit": "a.json", "data": {"n": 5, "seq": 5, "version": 1}},
        {"unit": "b.json", "data": {"n": 0, "seq": 0, "version": 1}},  # older than b's file: not taken
    ]
    text = "".join(json.dumps(x) + "\n" for x in whole)
    text += "{not json}\n"  # damaged
    text += json.dumps({"unit": "b.json", "data": {"n": 9, "seq": 9, "version": 1}})[:30]  # cut short by the crash
    (tmp_path / "journal.jsonl").write_text(text)
    caplog.set_level(logging.WARNING)
    a, b = AdminStore(tmp_path / "a.json"), AdminStore(tmp_path / "b.json")
    assert a.load() == {"n": 5, "version": 1} and a.seq == 5
    assert b.load() == {"n": 1, "version": 1} and b.seq == 1
    journal = tmp_path / "journal.jsonl"
    assert [r.getMessage() for r in caplog.records if "journal" in r.getMessage()] == [
        f"PackML admin journal {journal}: skipped 1 damaged line(s); the units' files are used for them"
    ]  # the line a crash cut short is not damage: never told durable
    writer = AdminWriter(asyncio.get_running_loop())
    b.writer = writer
    try:
        await _stored(b, {"n": 2})
        # before appending, the run folded what it found: a's newer data is in its file now
        assert _on_file(tmp_path / "a.json") == {"n": 5, "seq": 5, "version": 1}
        assert [(x["unit"], x["data"]["n"]) for x in _journal_lines(tmp_path)] == [("b.json", 2)]
    finally:
        await writer.close()
    assert AdminStore(tmp_path / "a.json").load() == {"n": 5, "version": 1}
    assert AdminStore(tmp_path / "b.json").load() == {"n": 2, "version": 1}


async def test_the_data_directory_removed_while_serving_is_made_again_and_nothing_goes_to_the_old_journal(
    tmp_path: Path,
) -> None:
    import shutil

    directory = tmp_path / "packml"
    writer = AdminWriter(asyncio.get_running_loop())
    store = AdminStore(directory / "a.json", writer)
    try:
        await _stored(store, {"n": 1})
        shutil.rmtree(directory)  # an operator's mistake while the server runs
        await _stored(store, {"n": 2})
        assert [x["data"]["n"] for x in _journal_lines(directory)] == [2]
        assert AdminStore(directory / "a.json").load() == {"n": 2, "version": 1}
    finally:
        await writer.close()
    assert _on_file(directory / "a.json") == {"n": 2, "seq": 2, "version": 1}
