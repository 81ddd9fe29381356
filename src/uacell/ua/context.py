"""Who is calling: the session and user behind the current service request.

asyncua passes neither the session nor the user to method callbacks. uacell wraps the session's
``call`` (and ``read``, for per-user attributes) once, so that a context variable holds the calling
session while the request runs; ``current_caller()`` turns it into a ``Caller``. While the method
dispatcher runs a method's behaviour, ``current_call()`` says which call it is (for the
AuditUpdateStateEvents of the transitions the call causes). Background tasks start in a fresh
context (``uacell.core.background``), so nothing they do is taken for a call's, except what completes a
call after it returned: the models run that in a copy of the call's context (decision 38).
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_session import InternalSession

from uacell.ua import door

_session: contextvars.ContextVar[InternalSession | None] = contextvars.ContextVar("uacell_session", default=None)
# The ReturnDiagnostics mask of the request being served (OPC 10000-4 RequestHeader).
_diagnostics: contextvars.ContextVar[int] = contextvars.ContextVar("uacell_diagnostics", default=0)
# The AuditEntryId of the request being served (OPC 10000-4 RequestHeader), "" when none.
_audit_entry: contextvars.ContextVar[str] = contextvars.ContextVar("uacell_audit_entry", default="")
_processor: contextvars.ContextVar[Any] = contextvars.ContextVar("uacell_processor", default=None)


@door.subclass("asyncua.crypto.permission_rules.User")
class UacellUser(User):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
    """An asyncua user that also carries uacell's role ("observer", "operator", "engineer", "admin")."""

    def __init__(
        self, name: str | None, uacell_role: str, anonymous: bool = False, *, certificate: bool = False
    ) -> None:
        # asyncua's own role only gates address-space management; uacell's roles gate everything else.
        super().__init__(role=UserRole.User, name=name)
        self.uacell_role = uacell_role
        self.anonymous = anonymous
        # how the user proved who they are, as OPC 10000-5 names it (SessionSecurityDiagnostics)
        self.mechanism = "Anonymous" if anonymous else "Certificate" if certificate else "UserName"
        self.expires: datetime | None = None  # when a certificate's credentials end (UTC), None: never
        # what the login was granted on (decision 99): the password's hash, or the certificate's SHA-256
        self.password_hash = ""
        self.certificate = ""

    def __repr__(self) -> str:
        return f"UacellUser({self.name!r}, {self.uacell_role})"


@dataclass(frozen=True)
class Caller:
    session_id: str
    session_name: str
    user: str | None
    role: str
    client: str = ""

    @property
    def display_user(self) -> str:
        return self.user or "anonymous"


INTERNAL = Caller("internal", "internal", None, "admin")


@dataclass(frozen=True)
class MethodCall:
    """A method call whose behaviour is running: who called what, with which inputs, when."""

    caller: Caller
    object_id: ua.NodeId
    method_id: ua.NodeId
    name: str  # the method's BrowseName
    inputs: tuple[ua.Variant, ...]
    started: datetime  # when the server took the call (an audit event's ActionTimeStamp)
    audit_entry_id: str = ""  # the client's AuditEntryId of the request


_call: contextvars.ContextVar[MethodCall | None] = contextvars.ContextVar("uacell_call", default=None)

# Post-processors of Read results: (session, read parameters, results) -> None (edits results in place).
ReadHook = Callable[[InternalSession, Any, list[Any]], None]
_read_hooks: list[ReadHook] = []


def session_text(session_id: Any) -> str:
    """A SessionId as the standard NodeId string (OPC 10000-6 5.3.1.10: ``ns=1;i=11``, ``ns=1;g=...``):
    what ``Caller.session_id`` holds and the audit trail writes."""
    to_string = getattr(session_id, "to_string", None)
    return str(to_string()) if callable(to_string) else str(session_id)


def session_name(session: Any) -> str:
    """The SessionName the client gave in CreateSession ("" if none): asyncua's own ``name`` of a
    session is its peer's address."""
    name = getattr(session, "session_name", None)
    return name if isinstance(name, str) else ""


def caller_of(session: InternalSession | None, default_role: str = "observer") -> Caller:
    if session is None:
        return INTERNAL
    user = session.user
    role = getattr(user, "uacell_role", default_role)
    # Kept on the session while its user and role stay (ActivateSession may change both).
    cached: tuple[Any, str, Caller] | None = door.tagged(session, "caller")
    if cached is not None and cached[0] is user and cached[1] == role:
        return cached[2]
    client = ""
    with_desc = getattr(session, "client_description", None)
    if with_desc is not None:
        client = getattr(with_desc, "ApplicationUri", "") or ""
    caller = Caller(session_text(session.session_id), session_name(session), getattr(user, "name", None), role, client)
    if with_desc is not None:  # the description is set at CreateSession, before any call
        door.tag(session, "caller", (user, role, caller))
    return caller


def set_return_diagnostics(mask: int) -> contextvars.Token[int]:
    return _diagnostics.set(mask)


def reset_return_diagnostics(token: contextvars.Token[int]) -> None:
    _diagnostics.reset(token)


def return_diagnostics() -> int:
    """The current request's ReturnDiagnostics bits (0: the client asked for none)."""
    return _diagnostics.get()


def current_caller() -> Caller:
    return caller_of(_session.get())


def set_audit_entry_id(entry: str) -> contextvars.Token[str]:
    return _audit_entry.set(entry)


def reset_audit_entry_id(token: contextvars.Token[str]) -> None:
    _audit_entry.reset(token)


def audit_entry_id() -> str:
    """The current request's AuditEntryId ("" when the client sent none)."""
    return _audit_entry.get()


def enter_call(call: MethodCall) -> contextvars.Token[MethodCall | None]:
    """The dispatcher runs ``call``'s behaviour from here until ``leave_call``."""
    return _call.set(call)


def leave_call(token: contextvars.Token[MethodCall | None]) -> None:
    _call.reset(token)


def current_call() -> MethodCall | None:
    """The method call whose behaviour is running in this task (None outside calls)."""
    return _call.get()


def add_read_hook(hook: ReadHook) -> None:
    if hook not in _read_hooks:
        _read_hooks.append(hook)


def run_read_hooks(session: InternalSession, params: Any, results: Any) -> None:
    """After a client's Read (``ua/pipeline.py``): each hook sees what was read."""
    for hook in _read_hooks:
        hook(session, params, results)


def set_session(session: InternalSession) -> contextvars.Token[InternalSession | None]:
    """The session whose Call, Read or HistoryRead runs from here (``ua/pipeline.py``)."""
    return _session.set(session)


def reset_session(token: contextvars.Token[InternalSession | None]) -> None:
    _session.reset(token)


def set_processor(processor: Any) -> contextvars.Token[Any]:
    """The connection's processor (asyncua ``UaProcessor``) of the request under way."""
    return _processor.set(processor)


def reset_processor(token: contextvars.Token[Any]) -> None:
    _processor.reset(token)


def current_processor() -> Any:
    """The asyncua ``UaProcessor`` of the request under way (None outside requests)."""
    return _processor.get()
