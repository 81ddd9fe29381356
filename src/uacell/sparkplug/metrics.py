"""Sparkplug's figures for ``/metrics`` ([metrics], docs/operations.md), read at scrape time."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from uacell.sparkplug.service import SparkplugService


class SparkplugCollector:
    def __init__(self, service: SparkplugService) -> None:
        self.service = service

    def collect(self) -> Iterator[Metric]:
        s, link = self.service, self.service.link
        yield CounterMetricFamily(
            "uacell_sparkplug_messages_sent", "Sparkplug messages the broker took", value=link.sent
        )
        yield CounterMetricFamily(
            "uacell_sparkplug_sessions", "Sparkplug sessions (MQTT connections, each a bdSeq)", value=link.connects
        )
        yield CounterMetricFamily(
            "uacell_sparkplug_connection_failures", "Broker connections that failed or dropped", value=link.failures
        )
        yield GaugeMetricFamily(
            "uacell_sparkplug_connected", "1 while connected to the broker", value=1 if link.connected.is_set() else 0
        )
        yield GaugeMetricFamily(
            "uacell_sparkplug_born", "1 while the edge node is born (and its primary host online)", value=int(s.live)
        )
