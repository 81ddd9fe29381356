"""Machinery's figures in ``/metrics`` (``Companion.metrics``): how many machines are in each
MachineryItemState and MachineryOperationMode (each machine's own states are in
``uacell_state_machine_state`` already, with every other state machine's)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import TYPE_CHECKING

from asyncua import ua
from prometheus_client.core import GaugeMetricFamily, Metric

from uacell.binding.metric_reads import cell_variables, variable_value

if TYPE_CHECKING:
    from uacell.host import Host

_ITEM = ".MachineryBuildingBlocks.MachineryItemState.CurrentState"
_MODE = ".MachineryBuildingBlocks.MachineryOperationMode.CurrentState"


class MachineCounts:
    """``uacell_machines{item_state, operation_mode}``: the number of machines in each pair."""

    def __init__(self, app: Host) -> None:
        self.app = app
        self._machines: list[tuple[ua.NodeId, ua.NodeId]] | None = None

    def collect(self) -> Iterator[Metric]:
        if self._machines is None:  # found once: their NodeIds follow the path
            nodes = dict(cell_variables(self.app))
            self._machines = [
                (node, nodes[path.removesuffix(_ITEM) + _MODE])
                for path, node in nodes.items()
                if path.endswith(_ITEM) and path.removesuffix(_ITEM) + _MODE in nodes
            ]
        counts: Counter[tuple[str, str]] = Counter()
        for item, mode in self._machines:
            texts = [variable_value(self.app, n) for n in (item, mode)]
            if all(isinstance(t, ua.LocalizedText) and t.Text for t in texts):
                counts[(texts[0].Text, texts[1].Text)] += 1
        gauge = GaugeMetricFamily(
            "uacell_machines", "OPC 40001-1 machines by MachineryItemState and MachineryOperationMode",
            labels=["item_state", "operation_mode"],
        )  # fmt: skip
        for (state, mode), count in sorted(counts.items()):
            gauge.add_metric([state, mode], count)
        yield gauge


def machinery_metrics(app: Host) -> MachineCounts:
    return MachineCounts(app)
