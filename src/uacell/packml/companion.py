"""OPC 30050 PackML as a uacell companion: everything the shared code needs to know, in one place."""

from __future__ import annotations

from typing import TYPE_CHECKING

from uacell.core.companion import Companion, Root, WebView, lazy_binder, lazy_metrics, package_file
from uacell.core.roles import Family, Role
from uacell.models.model_file import ModelFile
from uacell.packml.config import PackMLConfig, parse_units
from uacell.packml.datasets import PACKML_UNIT

if TYPE_CHECKING:  # the server's view, for the annotation only: loading the configuration stays light
    from uacell.host import ServerView

PACKML = Family("PackML")
UNIT_PART = "packml_unit"  # the part role (``uacell.binding.cell.Part.role``) the PackML binder binds

_OPERATOR_METHODS = (
    "Abort", "Clear", "Stop", "Reset", "Start", "Hold", "Unhold", "Suspend", "Unsuspend",
    "ToComplete", "SetUnitMode", "SetMachSpeed", "RemoteCommand", "SetInterlock",
)  # fmt: skip


# OPC 30050 needs only the base namespace.
PACKML_MODEL = ModelFile(
    "PackML",
    "http://opcfoundation.org/UA/PackML/",
    "Opc.Ua.PackML.NodeSet2.xml",
    "79016b1468d3288da36fca3604ad5439ebae7fdfca87e4f8def2aa1999e49adf",
    "package/nodesets/Opc.Ua.PackML.NodeSet2.xml",
)

PACKML_COMPANION: Companion[ServerView] = Companion(
    name="PackML",
    models=(PACKML_MODEL,),
    datasets=(PACKML_UNIT,),
    # Units: PackMLBaseObjectType (i=6) instances in PackMLObjects.
    web_view=WebView(
        "units",
        PACKML_MODEL.namespace_uri,
        "PackMLObjects",
        6,
        "uacell.packml.web_view:describe_unit",
        script=package_file(__package__, "static/view.js"),
        style=package_file(__package__, "static/view.css"),
        history="uacell.packml.web_view:unit_history",
    ),
    metrics=lazy_metrics("uacell.packml.metrics", "packml_metrics"),
    binder=lazy_binder("uacell.packml.binding", "bind_packml"),
    shape="uacell.packml.shape:shape_units",
    section="packml",
    settings=PackMLConfig,
    cell_section="packml_units",
    cell_parser=parse_units,
    # PackML units are organized by PackMLObjects (ns=PackML;i=72).
    roots=(Root("PackMLObjects", "PackML", 72, 35),),
    # SetMachSpeed and SetUnitMode are operator methods: they change how the unit runs now (speed,
    # Produce/Maintenance/Manual), as an operator does at the HMI; SetProduct and SetParameter change
    # what it makes and how, which is engineering; so is raising a fault on purpose (InjectFault).
    roles={
        **{(PACKML, m): Role.OPERATOR for m in _OPERATOR_METHODS},
        **{(PACKML, m): Role.ENGINEER for m in ("SetProduct", "SetParameter", "InjectFault")},
    },
    type_hints={
        "PackMLBaseObjectType": PACKML,
        "PackMLBaseStateMachineType": PACKML,
        "PackMLMachineStateMachineType": PACKML,
        "PackMLExecuteStateMachineType": PACKML,
    },
)
