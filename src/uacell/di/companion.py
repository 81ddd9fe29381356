"""DI (OPC 10000-100) as a uacell companion: DeviceSet and the LockingServices binder.

Which parts carry a Lock and which families a lock guards are the other companions' to say
(``Companion.locks``, ``Companion.lock_guarded``); ``uacell.di.locks`` binds what they declare.
"""

from __future__ import annotations

from uacell.companion import Companion, Root, lazy_binder
from uacell.roles import Family, Role

LOCKING = Family("Locking")

DI_LOCKING = Companion(
    name="DI",
    binder=lazy_binder("uacell.di.locks", "bind_locks"),
    # Devices are components of DeviceSet (ns=DI;i=5001).
    roots=(Root("DeviceSet", "DI", 5001, 47),),
    roles={
        **{(LOCKING, m): Role.OPERATOR for m in ("InitLock", "RenewLock", "ExitLock")},
        (LOCKING, "BreakLock"): Role.ENGINEER,
    },
    type_hints={"LockingServicesType": LOCKING, "Lock": LOCKING},
)
