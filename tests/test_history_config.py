"""[history] in the configuration file: each wrong value refused with a line naming it; a PostgreSQL
backend serves the same HistoryRead (and keeps it across a restart) as the embedded store."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from test_history_server import history, raw, set_speed
from test_history_store import postgres_dsn  # noqa: F401  (the module's PostgreSQL cluster)

from uacell.config import load_config
from uacell.core.errors import ConfigError


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('backend = "mysql"', r"\[history\] backend: must be 'sqlite' or 'postgresql'"),
        ('backend = "postgresql"', r"\[history\] postgresql_dsn: needed"),
        ("flush_interval = 0", r"\[history\] flush_interval: must be a positive number"),
        ("flush_interval = 100", r"\[history\] flush_interval: must be 0.01..60"),
        ("max_age_days = -1", r"\[history\] max_age_days: must be 0 \(no bound\) or more"),
        ("max_values_per_request = 0", r"\[history\] max_values_per_request: must be 1..1000000"),
        ("max_events_per_request = 0", r"\[history\] max_events_per_request: must be 1..100000"),
        ("max_events_per_request = 100001", r"\[history\] max_events_per_request: must be 1..100000"),
        ("flush = 1", r"\[history\] flush: unknown key"),
    ],
)
def test_wrong_history_settings_are_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "uacell.toml"
    path.write_text(f'[server]\ndata_dir = "{tmp_path / "data"}"\n[history]\n{text}\n')
    with pytest.raises(ConfigError, match=message):
        load_config(path)
    assert not (tmp_path / "data" / "history.sqlite").exists()


def test_history_settings_are_read(tmp_path: Path) -> None:
    path = tmp_path / "uacell.toml"
    path.write_text(
        '[history]\nbackend = "postgresql"\npostgresql_dsn = "host=db"\nflush_interval = 2\n'
        "max_age_days = 0\nmax_mb = 0\n"
    )
    h = load_config(path).history
    assert (h.backend, h.postgresql_dsn, h.flush_interval, h.enabled) == ("postgresql", "host=db", 2.0, True)
    assert (h.max_age_days, h.max_mb) == (0.0, 0.0)  # no bounds


async def test_a_server_on_postgresql_answers_and_keeps_history(tmp_path: Path, postgres_dsn: str) -> None:  # noqa: F811
    def config():
        c = fast_config(tmp_path / "data")
        c.history.backend = "postgresql"
        c.history.postgresql_dsn = postgres_dsn
        return c

    hour = timedelta(hours=1)
    for speed in (77.0, None):  # a first server writes, a second (a restart) reads it back
        app = await start_app(config())
        try:
            async with Client(app.endpoint, timeout=30) as client:
                ns = await client.get_namespace_index("urn:uacell:cell")
                node = ua.NodeId("Filler1.Status.MachSpeed", ns)
                if speed is not None:
                    await set_speed(client, ns, speed)
                assert app.history is not None
                await app.history.store.flush()
                now = datetime.now(UTC)
                (res,) = await history(client, raw(now - hour, now + hour), node)
                assert res.StatusCode.is_good()
                assert 77.0 in [dv.Value.Value for dv in res.HistoryData.DataValues]
        finally:
            await app.stop()
    assert not (tmp_path / "data" / "history.sqlite").exists()  # nothing went to the embedded store
