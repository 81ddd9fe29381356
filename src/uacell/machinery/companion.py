"""OPC 40001-1 Machinery as a uacell companion: everything the shared code needs to know, in one place.

Machinery adds no parts of its own: every robot and PackML unit the cell's other companions make is a
machine (``uacell.machinery.binding``). Its ``[[machines]]`` entries add identification to them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from uacell.core.companion import Companion, WebView, lazy_binder, lazy_metrics, package_file
from uacell.di.companion import DI_MODEL
from uacell.machinery.config import MachineryConfig, parse_machines
from uacell.machinery.datasets import DATASETS
from uacell.models.model_file import ModelFile
from uacell.robotics.companion import MODELS as ROBOTICS_MODELS

if TYPE_CHECKING:  # the server's view, for the annotation only: loading the configuration stays light
    from uacell.host import ServerView

MACHINERY_URI = "http://opcfoundation.org/UA/Machinery/"
BASE_URI = "http://opcfoundation.org/UA/"
MACHINES_FOLDER = 1001  # Machines, the well-known entry point (ns=Machinery;i=1001), in Objects

# OPC 40001-1 v1.04 builds on DI and on OPC 30001 Industrial Automation (IA).
IA_MODEL = next(m for m in ROBOTICS_MODELS if m.key == "IA")
MACHINERY_MODEL = ModelFile(
    "Machinery",
    MACHINERY_URI,
    "Opc.Ua.Machinery.NodeSet2.xml",
    "1bc4ba9f70d07c51d3310123f2ae2186703eb6cf4f2d26aea4a2853423b61b41",
    "package/nodesets/Opc.Ua.Machinery.NodeSet2.xml",
    requires=("DI", "IA"),
)

MACHINERY_COMPANION: Companion[ServerView] = Companion(
    name="Machinery",
    models=(DI_MODEL, IA_MODEL, MACHINERY_MODEL),
    datasets=DATASETS,
    # Machines: every object the Machines folder organizes, whatever its type (BaseObjectType, i=58).
    web_view=WebView(
        "machines",
        BASE_URI,
        "Machines",
        58,
        "uacell.machinery.web_view:describe_machine",
        script=package_file(__package__, "static/view.js"),
        style=package_file(__package__, "static/view.css"),
    ),
    metrics=lazy_metrics("uacell.machinery.metrics", "machinery_metrics"),
    binder=lazy_binder("uacell.machinery.binding", "bind_machinery"),
    shape="uacell.machinery.nodes:shape_machines",
    section="machinery",
    settings=MachineryConfig,
    cell_section="machines",
    cell_parser=parse_machines,
)
