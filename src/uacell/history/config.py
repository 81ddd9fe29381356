"""The ``[history]`` section (docs/configuration.md, docs/history.md)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class HistoryConfig:
    """[history]: what happened on the line (docs/history.md)."""

    enabled: bool = True
    backend: str = "sqlite"  # "sqlite" (history.sqlite in the data directory) or "postgresql"
    postgresql_dsn: str = ""  # the PostgreSQL connection string with backend = "postgresql"
    flush_interval: float = 0.5  # seconds between batch commits: the most a kill -9 loses
    max_age_days: float = 30.0  # 0: keep forever
    max_mb: float = 1024.0  # 0: no size bound
    max_values_per_request: int = 10_000  # per node and HistoryRead; more through continuation points
    max_events_per_request: int = 1_000  # events per node and HistoryRead (a page's work is bounded)
    axis_positions: bool = False  # also keep every robot axis' ActualPosition
