"""uacell's history on a real PostgreSQL (Debian's, a cluster of the test's own) that is unreachable
when uacell starts, and that goes away while it runs (docs/history.md, "PostgreSQL"): uacell serves
on, keeps what it records in memory, says so in one line, writes everything once the database answers
again; HistoryRead answers Bad_NoCommunication meanwhile."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import call_path, until, wait_until
from pg_cluster import PgCluster

from uacell.server import UacellServer

HOUR = timedelta(hours=1)


@pytest.fixture
def cluster() -> Iterator[PgCluster]:
    c = PgCluster()
    try:
        yield c
    finally:
        c.remove()


async def speeds(client: Client, ns: int) -> tuple[int, list[float]]:
    """The status and the MachSpeed values of the last hour."""
    details = ua.ReadRawModifiedDetails(
        IsReadModified=False,
        StartTime=datetime.now(UTC) - HOUR,
        EndTime=datetime.now(UTC) + HOUR,
        ReturnBounds=False,
    )
    params = ua.HistoryReadParameters(
        HistoryReadDetails=details,
        TimestampsToReturn=ua.TimestampsToReturn.Source,
        ReleaseContinuationPoints=False,
        NodesToRead=[ua.HistoryReadValueId(NodeId=ua.NodeId("Filler1.Status.MachSpeed", ns))],
    )
    (res,) = await client.uaclient.history_read(params)
    values = [dv.Value.Value for dv in res.HistoryData.DataValues] if res.HistoryData else []
    return res.StatusCode.value, values


async def set_speed(client: Client, speed: float) -> None:
    res = await call_path(client, "Filler1", "SetMachSpeed", ua.Variant(speed, ua.VariantType.Float))
    assert res.StatusCode.is_good(), res.StatusCode


def history_lines(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name.startswith("uacell.history")]


async def serve(tmp_path: Path, cluster: PgCluster) -> UacellServer:
    config = fast_config(tmp_path / "data")
    config.history.backend = "postgresql"
    config.history.postgresql_dsn = cluster.dsn
    return await start_app(config)


async def test_unreachable_at_start_then_up(
    tmp_path: Path, cluster: PgCluster, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="uacell.history")
    app = await serve(tmp_path, cluster)  # the cluster is not started: nothing listens on its port
    try:
        assert app.history is not None and app.history.store.down
        async with Client(app.endpoint, timeout=30, watchdog_intervall=30.0) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            for speed in (11.0, 12.0):
                await set_speed(client, speed)
            status, _ = await speeds(client, ns)
            assert status == ua.StatusCodes.BadNoCommunication
            cluster.start()
            # the table is created, everything recorded meanwhile is written
            await wait_until(lambda: not app.history.store.down, timeout=60)  # type: ignore[union-attr]

            async def arrived() -> bool:
                return (await speeds(client, ns))[1][-2:] == [11.0, 12.0]

            await until(arrived, True)
            status, values = await speeds(client, ns)
            assert status == ua.StatusCodes.Good and values[-2:] == [11.0, 12.0], values
        lines = history_lines(caplog)
        texts = [r.getMessage() for r in lines]
        assert all(r.levelno < logging.ERROR and r.exc_info is None for r in lines), texts
        assert sum("does not answer" in t for t in texts) == 1, texts  # one clear line when it starts
        assert sum("answers again" in t for t in texts) == 1, texts  # and one when it is back
    finally:
        await app.stop()


async def test_the_database_goes_away_and_comes_back(
    tmp_path: Path, cluster: PgCluster, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="uacell.history")
    cluster.start()
    app = await serve(tmp_path, cluster)
    try:
        assert app.history is not None and not app.history.store.down
        store = app.history.store
        async with Client(app.endpoint, timeout=30, watchdog_intervall=30.0) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            await set_speed(client, 21.0)
            await store.flush()
            assert (await speeds(client, ns))[1][-1] == 21.0
            cluster.stop()
            for speed in (22.0, 23.0, 24.0):
                await set_speed(client, speed)
            await wait_until(lambda: store.down, timeout=60)
            status, _ = await speeds(client, ns)
            assert status == ua.StatusCodes.BadNoCommunication
            await set_speed(client, 25.0)  # the cell serves on meanwhile
            cluster.start()
            await wait_until(lambda: not store.down, timeout=60)

            # the store answers again: every read is answered, also by a reader thread whose connection
            # is from before the stop (its read is asked again on a new connection)
            for _ in range(6):  # more reads than reader threads
                status, values = await speeds(client, ns)
                assert status == ua.StatusCodes.Good
                assert values[-5:] == [21.0, 22.0, 23.0, 24.0, 25.0], values  # nothing lost
            assert store.dropped == 0
        lines = history_lines(caplog)
        texts = [r.getMessage() for r in lines]
        assert all(r.levelno < logging.ERROR and r.exc_info is None for r in lines), texts
        assert sum("store does not answer" in t for t in texts) == 1, texts
        assert sum("store answers again" in t for t in texts) == 1, texts
        assert not any("a read failed" in t for t in texts), texts
    finally:
        await app.stop()


def test_a_read_on_a_connection_from_before_the_database_restarted_is_asked_again(cluster: PgCluster) -> None:
    """A reader thread keeps its connection; the database restarted meanwhile, its first read is
    answered all the same (on a new connection), and with the database gone it still fails."""
    from uacell.history.backends import Query
    from uacell.history.postgres import PostgresBackend

    cluster.start()
    backend = PostgresBackend(cluster.dsn)
    try:
        backend.write([("n", 1, 1, 0, 0, "", b"x")])
        query = Query("n", 0, None, None, False, 10)
        assert [s.seq for s in backend.read(query)] == [1]  # this thread's connection is made
        cluster.stop()
        cluster.start()
        assert [s.seq for s in backend.read(query)] == [1]
        cluster.stop()
        import psycopg

        with pytest.raises(psycopg.OperationalError):
            backend.read(query)
    finally:
        backend.close()
