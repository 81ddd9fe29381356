"""PackML's figures in ``/metrics`` (``Companion.metrics``): the Admin counters of every unit."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from asyncua import ua
from prometheus_client.core import GaugeMetricFamily, Metric

from uacell.binding.metric_reads import cell_variables, variable_value

if TYPE_CHECKING:
    from uacell.host import Host

COUNTERS = ("ProdProcessedCount", "ProdDefectiveCount", "ProdConsumedCount")


class PackMLCounters:
    """``uacell_packml_count{unit, counter, id, name}`` and ``uacell_packml_acc_count{...}``."""

    def __init__(self, app: Host) -> None:
        self.app = app
        self._counters: list[tuple[str, str, ua.NodeId]] | None = None

    def collect(self) -> Iterator[Metric]:
        if self._counters is None:  # found once: their NodeIds follow the path
            self._counters = [
                (path.removesuffix(f".Admin.{counter}"), counter, node)
                for path, node in cell_variables(self.app)
                for counter in COUNTERS
                if path.endswith(f".Admin.{counter}")
            ]
        count = GaugeMetricFamily(
            "uacell_packml_count", "PackML Admin counters: Count", labels=["unit", "counter", "id", "name"]
        )
        acc = GaugeMetricFamily(
            "uacell_packml_acc_count", "PackML Admin counters: AccCount", labels=["unit", "counter", "id", "name"]
        )
        for unit, counter, node in self._counters:
            for item in variable_value(self.app, node) or []:
                labels = [unit, counter, str(getattr(item, "ID", "")), str(getattr(item, "Name", ""))]
                count.add_metric(labels, float(getattr(item, "Count", 0)))
                acc.add_metric(labels, float(getattr(item, "AccCount", 0)))
        yield count
        yield acc


def packml_metrics(app: Host) -> PackMLCounters:
    return PackMLCounters(app)
