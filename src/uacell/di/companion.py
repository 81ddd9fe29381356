"""DI (OPC 10000-100) as a uacell companion: DeviceSet and the LockingServices binder.

Which parts carry a Lock and which families a lock guards are the other companions' to say
(``Companion.locks``, ``Companion.lock_guarded``); ``uacell.di.locks`` binds what they declare.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from uacell.core.companion import Companion, Root, lazy_binder
from uacell.core.roles import Family, Role
from uacell.models.model_file import ModelFile

if TYPE_CHECKING:  # the server's view, for the annotation only: loading the configuration stays light
    from uacell.host import ServerView

LOCKING = Family("Locking")

# OPC 10000-100 Devices: every companion builds on it.
DI_MODEL = ModelFile(
    "DI",
    "http://opcfoundation.org/UA/DI/",
    "Opc.Ua.Di.NodeSet2.xml",
    "40a02d98a8b2a014ec9f961625a422df3566d4dd783151ec6ae55b47296199de",
    "package/nodesets/Opc.Ua.Di.NodeSet2.xml",
)

DI_LOCKING: Companion[ServerView] = Companion(
    name="DI",
    models=(DI_MODEL,),
    binder=lazy_binder("uacell.di.locks", "bind_locks"),
    # Devices are components of DeviceSet (ns=DI;i=5001).
    roots=(Root("DeviceSet", "DI", 5001, 47),),
    roles={
        **{(LOCKING, m): Role.OPERATOR for m in ("InitLock", "RenewLock", "ExitLock")},
        (LOCKING, "BreakLock"): Role.ENGINEER,
    },
    type_hints={"LockingServicesType": LOCKING, "Lock": LOCKING},
)
