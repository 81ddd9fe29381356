"""The entries of a web page's event list, from the events its OPC UA session receives (pure):
a TransitionEvent makes an entry; the AuditUpdateStateEvent the server fires right after the
TransitionEvent of a transition a method call caused names who caused it (none follows a transition
that happened by itself)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from uacell.web.values import jsonable


def transition_entry(event: Any, machine: str | None, reason: Any) -> dict[str, Any]:
    """The page's entry for a TransitionEvent of ``machine`` (its key in the cell, if known), with the
    machine's LastTransitionReason as published just before the event."""
    source = getattr(event, "SourceNode", None)
    return {
        "time": jsonable(getattr(event, "Time", None)),
        "machine": machine or jsonable(getattr(event, "SourceName", "")),
        "transition": jsonable(getattr(event, "Transition", None)),
        "from": jsonable(getattr(event, "FromState", None)),
        "to": jsonable(getattr(event, "ToState", None)),
        "message": jsonable(getattr(event, "Message", None)),
        "reason": reason,
        "source": jsonable(source),
        "from_id": jsonable(getattr(event, "FromState/Id", None)),
        "to_id": jsonable(getattr(event, "ToState/Id", None)),
        "user": None,  # set by the AuditUpdateStateEvent that follows when a call caused it
    }


def attribute(entries: Iterable[dict[str, Any]], audit: Any) -> dict[str, Any] | None:
    """Name who caused the newest entry (``entries`` newest first) the AuditUpdateStateEvent ``audit``
    is about: the same machine, from and to state, no user yet. Returns that entry, or None."""
    key = (
        jsonable(getattr(audit, "SourceNode", None)),
        jsonable(getattr(audit, "OldStateId", None)),
        jsonable(getattr(audit, "NewStateId", None)),
    )
    for entry in entries:
        if entry["user"] is None and (entry["source"], entry["from_id"], entry["to_id"]) == key:
            entry["user"] = getattr(audit, "ClientUserId", None) or "anonymous"  # null: an anonymous session
            entry["method"] = str(getattr(audit, "SourceName", "") or "").removeprefix("Method/")
            return entry
    return None
