"""PubSub's figures for ``/metrics`` ([metrics], docs/operations.md), read at scrape time."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from uacell.pubsub.mqtt import MqttLink


class PubSubCollector:
    def __init__(self, link: MqttLink) -> None:
        self.link = link

    def collect(self) -> Iterator[Metric]:
        link = self.link
        yield CounterMetricFamily("uacell_pubsub_messages_sent", "PubSub messages the broker took", value=link.sent)
        yield CounterMetricFamily(
            "uacell_pubsub_messages_dropped", "PubSub messages dropped from a full buffer", value=link.dropped
        )
        yield CounterMetricFamily(
            "uacell_pubsub_connection_failures", "Broker connections that failed or dropped", value=link.failures
        )
        yield GaugeMetricFamily(
            "uacell_pubsub_buffered", "PubSub messages waiting for the broker", value=len(link.buffer)
        )
        yield GaugeMetricFamily(
            "uacell_pubsub_connected", "1 while connected to the broker", value=1 if link.connected.is_set() else 0
        )
