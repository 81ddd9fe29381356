"""An optional Prometheus endpoint (prometheus-client): ``[metrics] enabled = true``.

Served at ``http://<host>:<port>/metrics`` (default 127.0.0.1:9840, loopback only) by a small asyncio
HTTP responder on the server's own event loop. Per server, in its own registry:

- ``uacell_sessions``: open client sessions;
- ``uacell_calls_total{method, result}`` and ``uacell_call_duration_seconds{method}`` (histogram);
- ``uacell_state_machine_state{machine, state}``: 1 for each state machine's current state;
- each companion's own (``Companion.metrics``), e.g. PackML's ``uacell_packml_count{unit, counter, id,
  name}`` and ``uacell_packml_acc_count{...}`` (``uacell.packml.metrics``).

States and counters are read from the address space when scraped, so they are exactly what clients see.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING

from asyncua import ua

from uacell.binding.metric_reads import cell_variables, variable_value
from uacell.core.companion import Companion
from uacell.core.errors import ConfigError
from uacell.core.extras import MissingExtra
from uacell.ua.channel import session_count
from uacell.ua.context import Caller

try:
    from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
    from prometheus_client.core import GaugeMetricFamily, Metric
    from prometheus_client.exposition import CONTENT_TYPE_LATEST
except ImportError as exc:  # the 'metrics' extra
    raise MissingExtra.of("[metrics]", exc) from exc

if TYPE_CHECKING:
    from uacell.host import Host, ServerView

log = logging.getLogger(__name__)
_A = ua.AttributeIds
_MAX_REQUEST = 8192


class _AddressSpaceCollector:
    """Sessions and current states, read at scrape time."""

    def __init__(self, app: Host) -> None:
        self.app = app
        self._states: list[tuple[str, ua.NodeId]] | None = None

    def collect(self) -> Iterator[Metric]:
        if self._states is None:  # every CurrentState, found once (their NodeIds follow the path)
            found = [
                (p.removesuffix(".CurrentState"), n) for p, n in cell_variables(self.app) if p.endswith(".CurrentState")
            ]
            self._states = sorted(found, key=lambda s: s[0])
        sessions = GaugeMetricFamily("uacell_sessions", "Open client sessions")
        sessions.add_metric([], session_count(self.app.server.iserver))
        yield sessions
        states = GaugeMetricFamily(
            "uacell_state_machine_state", "1 for the current state of each state machine", labels=["machine", "state"]
        )
        for machine, node in self._states:
            value = variable_value(self.app, node)
            if isinstance(value, ua.LocalizedText) and value.Text:
                states.add_metric([machine, value.Text], 1)
        yield states


class Metrics:
    """The metrics of one server and, once started, the endpoint that serves them."""

    def __init__(self, app: ServerView, companions: Iterable[Companion[ServerView]]) -> None:
        self.registry = CollectorRegistry()
        self.calls = Counter(
            "uacell_calls", "Method calls by method and result", ["method", "result"], registry=self.registry
        )
        self.latency = Histogram(
            "uacell_call_duration_seconds",
            "Time to answer a method call",
            ["method"],
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0),
        )
        self.registry.register(_AddressSpaceCollector(app))
        for companion in companions:  # each companion's own figures (Companion.metrics)
            if companion.metrics is not None:
                self.registry.register(companion.metrics(app))
        app.dispatcher.observers.append(self._on_call)
        self._server: asyncio.Server | None = None
        self.port = 0

    def _on_call(
        self, _caller: Caller, _request: ua.CallMethodRequest, method: str, result: ua.CallMethodResult, seconds: float
    ) -> None:
        name = method or "unknown"
        self.calls.labels(name, str(result.StatusCode.name)).inc()
        self.latency.labels(name).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)

    async def start(self, host: str, port: int) -> None:
        try:
            self._server = await asyncio.start_server(self._serve, host, port)
        except OSError as exc:
            raise ConfigError(f"cannot serve metrics on {host}:{port}: {exc.strerror or exc}") from exc
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("metrics at http://%s:%d/metrics", host, self.port)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10.0)
            request_line = head[:_MAX_REQUEST].split(b"\r\n", 1)[0].decode("latin-1").split()
            if len(request_line) >= 2 and request_line[0] in ("GET", "HEAD") and request_line[1] in ("/metrics", "/"):
                body, status, ctype = self.render(), "200 OK", CONTENT_TYPE_LATEST
            else:
                body, status, ctype = b"not found: try /metrics\n", "404 Not Found", "text/plain"
            if request_line and request_line[0] == "HEAD":
                body_out = b""
            else:
                body_out = body
            writer.write(
                f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                "Connection: close\r\n\r\n".encode()
                + body_out
            )
            await writer.drain()
        except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass
        except Exception:
            log.exception("metrics request failed")
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()
