"""What the server tells its audit trail: method calls, writes and program file changes.

Logins and sessions are recorded by ``uacell.security.policy``, which sees them first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from asyncua import ua

from uacell.security.audit import AuditTrail
from uacell.ua.attributes import attribute_name
from uacell.ua.context import Caller, session_name, session_text

if TYPE_CHECKING:
    from uacell.host import Host


def _status_name(code: ua.StatusCode) -> str:
    return str(code.name)


def _plain(value: Any) -> Any:
    """A JSON-friendly form of a written or returned value (kept short)."""
    if isinstance(value, bool | int | float | str) or value is None:
        return value if not isinstance(value, str) or len(value) <= 200 else value[:200] + "..."
    if isinstance(value, list):
        return [_plain(v) for v in value[:20]]
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    text = str(value)
    return text if len(text) <= 200 else text[:200] + "..."


_TEXTS_KEPT = 4096  # NodeId texts kept for the audit records (the objects clients call); then begun anew


def install_audit(app: Host, trail: AuditTrail) -> None:
    dispatcher = app.dispatcher
    texts: dict[ua.NodeId, str] = {}

    def text(node_id: ua.NodeId) -> str:
        found = texts.get(node_id)
        if found is None:
            if len(texts) >= _TEXTS_KEPT:
                texts.clear()
            found = texts[node_id] = node_id.to_string()
        return found

    def call(
        caller: Caller, request: ua.CallMethodRequest, method: str, result: ua.CallMethodResult, _s: float
    ) -> None:
        fields: dict[str, Any] = {
            "user": caller.display_user,
            "role": caller.role,
            "session": caller.session_id,
            "object": text(request.ObjectId),
            "method": method,
            "result": _status_name(result.StatusCode),
        }
        bound = dispatcher.methods.get(request.MethodId)
        if bound is not None and result.OutputArguments:
            names = [a.Name for a in bound.outputs]
            if "Status" in names and names.index("Status") < len(result.OutputArguments):
                fields["status_output"] = _plain(result.OutputArguments[names.index("Status")].Value)
        if result.InputArgumentResults and any(not r.is_good() for r in result.InputArgumentResults):
            fields["argument_results"] = [_status_name(r) for r in result.InputArgumentResults]
        trail.record("call", **fields)

    def write(caller: Caller, item: ua.WriteValue, status: ua.StatusCode) -> None:
        value = item.Value.Value.Value if item.Value is not None and item.Value.Value is not None else None
        trail.record(
            "write",
            user=caller.display_user,
            role=caller.role,
            session=caller.session_id,
            node=item.NodeId.to_string(),
            attribute=attribute_name(item.AttributeId),
            value=_plain(value),
            result=_status_name(status),
        )

    dispatcher.observers.append(call)
    app.writes.observers.append(write)


def session_fields(session: Any) -> dict[str, Any]:
    """Who a session is, for the audit trail."""
    description = getattr(session, "client_description", None)
    user = getattr(session, "user", None)
    return {
        "session": session_text(session.session_id),
        "session_name": session_name(session),
        "user": getattr(user, "name", None) or "anonymous",
        "application_uri": getattr(description, "ApplicationUri", "") or "",
    }
