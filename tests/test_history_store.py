"""The history store's conformance tests, run on both backends (SQLite, PostgreSQL), plus kill -9.

PostgreSQL: the test starts its own cluster (initdb/pg_ctl, as the ``postgres`` user when run as root)
on a free loopback port in a temporary directory and stops it; without Debian's postgresql these skip.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pg_cluster import PgCluster

from uacell.history.backends import EVENT, VALUE, Backend, Query, SqliteBackend
from uacell.history.store import ContinuationPointInvalid, Cursor, HistoryStore, StoreSettings

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def postgres_dsn() -> Iterator[str]:
    cluster = PgCluster()
    try:
        try:
            cluster.start()
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
            pytest.skip(f"could not start PostgreSQL: {e}")
        yield cluster.dsn
    finally:
        cluster.remove()


_tables = iter(range(10**6))
KEEP = StoreSettings(max_age_days=0, max_mb=0)  # the samples below are from 1970: no retention


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Backend]:
    if request.param == "sqlite":
        b: Backend = SqliteBackend(tmp_path / "history.sqlite")
    else:
        from uacell.history.postgres import PostgresBackend

        b = PostgresBackend(request.getfixturevalue("postgres_dsn"), table=f"t{os.getpid()}_{next(_tables)}")
    yield b
    b.close()


async def fill(store: HistoryStore, node: str, n: int, per_time: int, t0: int = 1_000_000, kind: int = VALUE) -> None:
    for i in range(n):
        store.record(node, t0 + (i // per_time), kind, 0, "", i.to_bytes(4, "big"))
    await store.flush()


def numbers(samples: list[Any]) -> list[int]:
    return [int.from_bytes(s.data, "big") for s in samples]


async def page_all(store: HistoryStore, q: Query, page: int) -> list[int]:
    out: list[int] = []
    after = None
    while True:
        rows = await store.read(Query(q.node, q.kind, q.lo, q.hi, q.reverse, page, after, q.lo_inclusive))
        out += numbers(rows)
        if len(rows) < page:
            return out
        after = (rows[-1].time, rows[-1].seq)


async def test_pages_neither_repeat_nor_skip_equal_timestamps(backend: Backend) -> None:
    store = HistoryStore(backend, KEEP)
    store.start()
    await fill(store, "a", 5_000, per_time=250)
    await fill(store, "b", 10, per_time=1)  # another node, not read
    forward = await page_all(store, Query("a", VALUE, None, None, False, 0), page=333)
    assert forward == list(range(5_000))
    backward = await page_all(store, Query("a", VALUE, None, None, True, 0), page=97)
    assert backward == list(range(4_999, -1, -1))
    # bounds: lo inclusive, hi exclusive
    inside = await page_all(store, Query("a", VALUE, 1_000_001, 1_000_003, False, 0), page=100)
    assert inside == list(range(250, 750))
    assert await store.read(Query("a", EVENT, None, None, False, 10)) == []
    await store.close()


async def test_restart_keeps_samples_and_numbers_on(backend: Backend, tmp_path: Path) -> None:
    store = HistoryStore(backend, KEEP)
    store.start()
    await fill(store, "a", 100, per_time=10)
    top = backend.max_seq()
    assert top >= 100
    store2 = HistoryStore(backend, KEEP)  # as after a restart: numbering continues above what is stored
    store2.record("a", 1_000_009, VALUE, 0, "", (100).to_bytes(4, "big"))
    await store2.flush()
    assert numbers(await store2.read(Query("a", VALUE, None, None, False, 1000))) == list(range(101))
    assert backend.max_seq() == top + 1


async def test_retention_by_age_and_size(backend: Backend) -> None:
    now = [2_000.0]
    store = HistoryStore(backend, StoreSettings(max_age_days=1.0, max_mb=0), now=lambda: now[0])
    day = 86_400 * 1_000_000
    for i in range(10):
        store.record("a", i * day // 4, VALUE, 0, "", i.to_bytes(4, "big"))  # every 6 hours from the epoch
    await store.flush()
    now[0] = 2 * 86_400.0  # two days after the epoch: keep the last day only
    store.prune()
    assert numbers(await store.read(Query("a", VALUE, None, None, False, 100))) == [4, 5, 6, 7, 8, 9]
    for i in range(20_000):
        store.record("b", 3 * day + i, VALUE, 0, "", b"x" * 100)
    await store.flush()
    big = HistoryStore(backend, StoreSettings(max_age_days=0, max_mb=0.5))
    big.prune()
    left = await store.read(Query("b", VALUE, None, None, False, 100_000))
    assert 0 < len(left) < 20_000
    assert left[-1].time == 3 * day + 19_999  # the newest stay
    assert left[0].time == 3 * day + 20_000 - len(left)  # what is gone is the oldest


def test_continuation_points_are_opaque_and_checked() -> None:
    cursor = Cursor()
    point = cursor.encode("ns=1;s=x", 123, 456)
    assert cursor.decode("ns=1;s=x", point) == (123, 456)
    for bad in (point[:-1], point[:-1] + bytes([point[-1] ^ 1]), b"", b"x" * len(point)):
        with pytest.raises(ContinuationPointInvalid):
            cursor.decode("ns=1;s=x", bad)
    with pytest.raises(ContinuationPointInvalid):
        cursor.decode("ns=1;s=y", point)  # another node's
    with pytest.raises(ContinuationPointInvalid):
        Cursor().decode("ns=1;s=x", point)  # another server start's


_WRITER = textwrap.dedent(
    """
    import asyncio, sys, time
    from pathlib import Path
    from uacell.history.backends import SqliteBackend, VALUE
    from uacell.history.store import HistoryStore, StoreSettings

    async def main():
        settings = StoreSettings(flush_interval=0.2, max_age_days=0, max_mb=0)
        store = HistoryStore(SqliteBackend(Path(sys.argv[1])), settings)
        store.start()
        i = 0
        while True:
            for _ in range(50):
                store.record("a", 1_000_000 + i, VALUE, 0, "", i.to_bytes(4, "big"))
                i += 1
            print("committed", store.written, "recorded", i, flush=True)
            await asyncio.sleep(0.005)

    asyncio.run(main())
    """
)


def test_kill_9_during_a_batch_loses_at_most_the_last_interval(tmp_path: Path) -> None:
    db = tmp_path / "history.sqlite"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(db)], stdout=subprocess.PIPE, text=True, env=env)
    committed = 0
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            committed = int(line.split()[1])
            if committed >= 3_000:
                break
        proc.send_signal(signal.SIGKILL)  # while the writer keeps recording and committing
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    kept = [int.from_bytes(r[0], "big") for r in con.execute("SELECT data FROM samples ORDER BY seq")]
    con.close()
    assert committed >= 3_000
    assert kept == list(range(len(kept)))  # whole batches: a prefix, no gap
    assert len(kept) >= committed  # everything reported committed survived


def test_an_event_is_encoded_field_by_field_the_repeating_ones_once() -> None:
    """encode_fields writes each field that has a value as its name and Variant, the same bytes whether
    a field's encoding is taken from the repeating fields' cache or made anew; decode_fields reads
    them back."""
    from datetime import UTC, datetime

    from asyncua import ua

    from uacell.history import service

    V = ua.VariantType
    types = {
        "EventType": V.NodeId, "SourceName": V.String, "Severity": V.UInt16, "Message": V.LocalizedText,
        "Time": V.DateTime, "EventId": V.ByteString, "InputArguments": V.Variant, "Missing": V.String,
    }  # fmt: skip
    values = {
        "EventType": ua.NodeId(2311), "SourceName": "TaskControl1", "Severity": 100,
        "Message": ua.LocalizedText("Idle to Ready"), "Time": datetime(2026, 11, 26, tzinfo=UTC),
        "EventId": b"0123456789abcdef", "InputArguments": [ua.Variant("pick", V.String)], "Missing": None,
        "internal": "not a field", "__private": 1,
    }  # fmt: skip
    service._REPEATING.clear()
    first = service.encode_fields(values, service.event_plan(types, skip=("internal",)))
    assert service._REPEATING  # the repeating fields were kept
    again = service.encode_fields(values, service.event_plan(types, skip=("internal",)))
    assert again == first
    fields = service.decode_fields(first)
    assert list(fields) == ["EventType", "SourceName", "Severity", "Message", "Time", "EventId", "InputArguments"]
    assert fields["SourceName"] == ua.Variant("TaskControl1", V.String)
    assert fields["Severity"].Value == 100 and fields["Severity"].VariantType == V.UInt16
    assert fields["Message"].Value == ua.LocalizedText("Idle to Ready")
    assert fields["InputArguments"].Value == [ua.Variant("pick", V.String)]
    service._REPEATING.clear()  # made anew, field by field: the same bytes
    assert service.encode_fields(values, service.event_plan(types, skip=("internal",))) == first
    # the times and EventIds, written out, are the bytes asyncua's Variant encoding gives
    for name, vtype, value in (
        ("Time", V.DateTime, datetime(2026, 11, 26, 7, 8, 9, 123456, tzinfo=UTC)),
        ("ReceiveTime", V.DateTime, datetime(1601, 1, 1, tzinfo=UTC)),
        ("EventId", V.ByteString, b""),
        ("EventId", V.ByteString, bytes(range(40))),
        ("EventId", V.ByteString, ua.Variant(bytes(range(16)), V.ByteString)),  # as the emitters give it
    ):
        assert service._encoded(name, vtype, value) == service._field(name, vtype, value)


def test_localized_texts_and_status_codes_are_kept_by_what_they_encode() -> None:
    """asyncua's LocalizedText, StatusCode and TimeZoneDataType are not hashable, yet a state's name, a
    Message, a StatusCodeId and LocalTime repeat from event to event: they are kept by their locale and
    text, their code, their offset and daylight flag, so a text in another locale, or another text,
    another code or another zone is never taken for a kept one."""
    from asyncua import ua

    from uacell.history import service

    V = ua.VariantType
    service._REPEATING.clear()
    cases = [
        ("Message", V.LocalizedText, ua.LocalizedText("Idle to Ready")),
        ("Message", V.LocalizedText, ua.LocalizedText("Idle to Ready", "en")),
        ("Message", V.LocalizedText, ua.LocalizedText("Ready to Idle")),
        ("StatusCodeId", V.StatusCode, ua.StatusCode(ua.StatusCodes.Good)),
        ("StatusCodeId", V.StatusCode, ua.StatusCode(ua.StatusCodes.BadInvalidState)),
        ("LocalTime", V.ExtensionObject, ua.TimeZoneDataType(Offset=60, DaylightSavingInOffset=False)),
        ("LocalTime", V.ExtensionObject, ua.TimeZoneDataType(Offset=60, DaylightSavingInOffset=True)),
        ("LocalTime", V.ExtensionObject, ua.TimeZoneDataType(Offset=-60, DaylightSavingInOffset=False)),
    ]
    made = [service._encoded(name, vtype, value) for name, vtype, value in cases]
    assert len(service._REPEATING) == len(cases)  # each kept, none taken for another
    assert len(set(made)) == len(cases)
    for (name, vtype, value), encoded in zip(cases, made, strict=True):
        assert encoded == service._field(name, vtype, value)  # asyncua's bytes
        assert service._encoded(name, vtype, value) is service._REPEATING[(name, vtype, service._hashable(value))]
    assert service.decode_fields(made[1])["Message"].Value == ua.LocalizedText("Idle to Ready", "en")


async def test_an_event_fired_through_two_notifiers_is_kept_for_each_and_encoded_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A firing reaches history once per historized notifier (the machine's node, the Server): a row
    for each, from one encoding; the next firing (a new EventId) is encoded anew."""
    from datetime import UTC, datetime

    from asyncua import ua
    from asyncua.common.event_objects import BaseEvent

    from uacell.history import service

    calls: list[bytes] = []
    real = service.encode_fields

    def counting(*args: object) -> bytes:
        data = real(*args)  # type: ignore[arg-type]
        calls.append(data)
        return data

    monkeypatch.setattr(service, "encode_fields", counting)
    store = HistoryStore(SqliteBackend(tmp_path / "h.sqlite"))
    history = service.HistoryService(None, store, lambda role: True)
    machine, server = ua.NodeId("TC", 2), ua.NodeId(ua.ObjectIds.Server)
    history.notifiers = {machine: "ns=2;s=TC", server: "i=2253"}
    event = BaseEvent()
    for n, when in enumerate((datetime(2026, 11, 26, 1, tzinfo=UTC), datetime(2026, 11, 26, 2, tzinfo=UTC))):
        event.EventId, event.Time, event.Message = bytes([n]) * 16, when, ua.LocalizedText(f"firing {n}")
        for notifier in (machine, server):
            event.emitting_node = notifier
            history._on_event(event)
    await store.flush()
    assert len(calls) == 2  # one encoding a firing
    for key in ("ns=2;s=TC", "i=2253"):
        rows = await store.read(Query(key, EVENT, None, None, False, 10))
        fields = [service.decode_fields(r.data) for r in rows]
        assert [f["Message"].Value.Text for f in fields] == ["firing 0", "firing 1"]
        assert [f["EventId"].Value for f in fields] == [bytes([0]) * 16, bytes([1]) * 16]
    await store.close()


def test_a_kept_value_is_encoded_as_asyncua_does_the_repeating_ones_once() -> None:
    """encode_value gives asyncua's bytes for every kind of value; a scalar that repeats is encoded
    once, by its type and value (a value of another type or another value is never taken for it), and
    a float never is: 0.0 and -0.0 are one key but two encodings."""
    from asyncua import ua
    from asyncua.ua.ua_binary import variant_from_binary, variant_to_binary

    from uacell.history import service

    V = ua.VariantType
    cases = [
        ua.Variant(ua.LocalizedText("Ready"), V.LocalizedText),
        ua.Variant(ua.LocalizedText("Ready", "en"), V.LocalizedText),
        ua.Variant(ua.NodeId(2311), V.NodeId),
        ua.Variant(True, V.Boolean),
        ua.Variant(1, V.Int32),
        ua.Variant(1, V.UInt32),
        ua.Variant("PickAndPlace", V.String),
        ua.Variant(0.0, V.Double),
        ua.Variant(-0.0, V.Double),
        ua.Variant(-0.0, V.Float),
        ua.Variant(float("nan"), V.Double),
        ua.Variant([1, 2], V.Int32, is_array=True),
        ua.Variant(ua.EUInformation(UnitId=4408652), V.ExtensionObject),
        ua.Variant(),
    ]
    service._VALUES.clear()
    for _ in range(2):
        for variant in cases:
            encoded = service.encode_value(variant)
            assert encoded == variant_to_binary(variant), variant
    back = variant_from_binary(ua.utils.Buffer(service.encode_value(ua.Variant(-0.0, V.Double))))
    assert str(back.Value) == "-0.0"
    # kept: the two texts, the NodeId, the flag, the two integers (one per type), the string, null
    assert len(service._VALUES) == 8


async def test_an_event_objects_fields_are_planned_once(tmp_path: Path) -> None:
    """The fields an event is kept with are worked out once for each event object and give the
    bytes a plan made anew gives; an object whose types grew gets a new plan."""
    from asyncua import ua

    from uacell.history import service
    from uacell.history.service import HistoryService

    V = ua.VariantType

    class FakeEvent:  # what an asyncua Event holds: fields as attributes, their types, internal names
        Message: ua.LocalizedText  # set by the test below (declared only: vars() holds what is set)

        def __init__(self) -> None:
            self.data_types = {"SourceName": V.String, "Severity": V.UInt16, "internal": V.String}
            self.internal_properties = ("internal",)
            self.SourceName, self.Severity, self.internal = "TaskControl1", 100, "x"

    store = HistoryStore(SqliteBackend(tmp_path / "h.sqlite"))
    history = HistoryService(None, store, lambda role: True)
    event = FakeEvent()
    plan = history._event_plan(event)
    assert plan == (("SourceName", V.String), ("Severity", V.UInt16))
    assert history._event_plan(event) is plan
    values = dict(vars(event))
    fresh = service.event_plan(event.data_types, ("internal",))
    assert plan == fresh and service.encode_fields(values, plan) == service.encode_fields(values, fresh)
    event.data_types["Message"] = V.LocalizedText
    event.Message = ua.LocalizedText("Idle to Ready")
    assert history._event_plan(event)[-1] == ("Message", V.LocalizedText)
    assert history._event_plan(FakeEvent()) == plan  # another object of the same kind: the same fields
    await store.close()
