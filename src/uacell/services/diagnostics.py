"""OPC UA server diagnostics (OPC 10000-5, 6.3.3 ServerDiagnosticsType), which asyncua leaves empty.

Kept current by uacell: ``EnabledFlag`` (true), ``ServerDiagnosticsSummary`` (the structure and its
component variables), ``SessionsDiagnosticsSummary/SessionDiagnosticsArray`` and
``SessionSecurityDiagnosticsArray``. The counts come from the request hook in ``uacell.security.policy`` (every
service request of every session passes it) and from the session life cycle; the values are written
after each session change and once a second, only where something changed, so subscriptions see them.

``SessionSecurityDiagnosticsArray`` holds client certificates and user names: only ``admin`` may read it
(others get Bad_UserAccessDenied). Not kept: per-session diagnostics objects, SubscriptionDiagnostics
and SamplingIntervalDiagnostics (they stay empty, as before), CurrentPublishRequestsInQueue (0).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from asyncua import ua
from asyncua.common.utils import ServiceError

from uacell.ua import door
from uacell.ua.door import connection as door_connection
from uacell.ua.pipeline import Next, Request

if TYPE_CHECKING:
    from asyncua.server.internal_session import InternalSession
    from asyncua.server.uaprocessor import UaProcessor

    from uacell.host import Host

log = logging.getLogger(__name__)

_O = ua.ObjectIds
ENABLED_FLAG = ua.NodeId(_O.Server_ServerDiagnostics_EnabledFlag)
SUMMARY = ua.NodeId(_O.Server_ServerDiagnostics_ServerDiagnosticsSummary)
SESSIONS = ua.NodeId(_O.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionDiagnosticsArray)
SECURITY = ua.NodeId(_O.Server_ServerDiagnostics_SessionsDiagnosticsSummary_SessionSecurityDiagnosticsArray)
REFRESH_SECONDS = 1.0

# Request encodings -> the SessionDiagnosticsDataType counter they count in.
_SERVICES = {
    "Read": "ReadCount", "HistoryRead": "HistoryReadCount", "Write": "WriteCount",
    "HistoryUpdate": "HistoryUpdateCount", "Call": "CallCount", "CreateMonitoredItems": "CreateMonitoredItemsCount",
    "ModifyMonitoredItems": "ModifyMonitoredItemsCount", "SetMonitoringMode": "SetMonitoringModeCount",
    "SetTriggering": "SetTriggeringCount", "DeleteMonitoredItems": "DeleteMonitoredItemsCount",
    "CreateSubscription": "CreateSubscriptionCount", "ModifySubscription": "ModifySubscriptionCount",
    "SetPublishingMode": "SetPublishingModeCount", "Publish": "PublishCount", "Republish": "RepublishCount",
    "TransferSubscriptions": "TransferSubscriptionsCount", "DeleteSubscriptions": "DeleteSubscriptionsCount",
    "AddNodes": "AddNodesCount", "AddReferences": "AddReferencesCount", "DeleteNodes": "DeleteNodesCount",
    "DeleteReferences": "DeleteReferencesCount", "Browse": "BrowseCount", "BrowseNext": "BrowseNextCount",
    "TranslateBrowsePathsToNodeIds": "TranslateBrowsePathsToNodeIdsCount", "QueryFirst": "QueryFirstCount",
    "QueryNext": "QueryNextCount", "RegisterNodes": "RegisterNodesCount", "UnregisterNodes": "UnregisterNodesCount",
}  # fmt: skip
_BY_TYPEID = {
    ua.NodeId(getattr(_O, f"{service}Request_Encoding_DefaultBinary")): counter
    for service, counter in _SERVICES.items()
    if hasattr(_O, f"{service}Request_Encoding_DefaultBinary")
}
_CREATE_SESSION = ua.NodeId(_O.CreateSessionRequest_Encoding_DefaultBinary)
_ACTIVATE_SESSION = ua.NodeId(_O.ActivateSessionRequest_Encoding_DefaultBinary)
_CLOSE_SESSION = ua.NodeId(_O.CloseSessionRequest_Encoding_DefaultBinary)
_CREATE_SUBSCRIPTION = ua.NodeId(_O.CreateSubscriptionRequest_Encoding_DefaultBinary)
# Requests that change a session or what the summary counts: the values are refreshed at once. Any other
# request only moves its session's counters, which the once-a-second refresh publishes (a refresh after
# every request would cost every call the whole session array).
_AT_ONCE = {_CREATE_SESSION, _ACTIVATE_SESSION, _CLOSE_SESSION, _CREATE_SUBSCRIPTION} | {
    ua.NodeId(getattr(_O, f"{service}Request_Encoding_DefaultBinary"))
    for service in ("DeleteSubscriptions", "TransferSubscriptions", "CreateMonitoredItems", "DeleteMonitoredItems")
}
_SECURITY_CODES = {
    getattr(ua.StatusCodes, name)
    for name in (
        "BadUserAccessDenied", "BadIdentityTokenRejected", "BadIdentityTokenInvalid", "BadSecurityChecksFailed",
        "BadCertificateUntrusted", "BadCertificateInvalid", "BadCertificateTimeInvalid", "BadCertificateUriInvalid",
        "BadApplicationSignatureInvalid", "BadUserSignatureInvalid", "BadSecurityModeRejected",
        "BadSecurityPolicyRejected",
    )
}  # fmt: skip


@dataclass
class SessionSecurityDiagnosticsDataType:
    """OPC 10000-5 12.12 SessionSecurityDiagnosticsDataType, encoded as the standard says.

    asyncua 2.1.0 takes any structure field named ``Encoding`` for the optional-field mask and sends a
    Byte where this String belongs, which other clients cannot decode. This class (registered for the
    type's encoding in place of asyncua's) calls the field ``TransportEncoding``; on the wire it is the
    standard's ``Encoding`` String.
    """

    data_type = ua.NodeId(ua.ObjectIds.SessionSecurityDiagnosticsDataType)

    SessionId: ua.NodeId = field(default_factory=ua.NodeId)
    ClientUserIdOfSession: ua.String = None
    ClientUserIdHistory: list[ua.String] = field(default_factory=list)
    AuthenticationMechanism: ua.String = None
    TransportEncoding: ua.String = None
    TransportProtocol: ua.String = None
    SecurityMode: ua.MessageSecurityMode = ua.MessageSecurityMode.Invalid
    SecurityPolicyUri: ua.String = None
    ClientCertificate: ua.ByteString = None


def _key(session: Any) -> str:
    """A session's key in ``Diagnostics.sessions`` (its SessionId as text, made once per session)."""
    key: str | None = door.tagged(session, "key")
    if key is None:
        key = str(session.session_id)
        door.tag(session, "key", key)
    return key


def _register_corrected_types() -> None:
    uatypes_log = logging.getLogger("asyncua.ua.uatypes")
    disabled = uatypes_log.disabled
    uatypes_log.disabled = True  # asyncua announces every registration at INFO
    try:
        ua.register_extension_object(
            "SessionSecurityDiagnosticsDataType",
            ua.NodeId(ua.ObjectIds.SessionSecurityDiagnosticsDataType_Encoding_DefaultBinary),
            SessionSecurityDiagnosticsDataType,
            ua.NodeId(ua.ObjectIds.SessionSecurityDiagnosticsDataType),
        )
    finally:
        uatypes_log.disabled = disabled


_register_corrected_types()


@dataclass
class SessionRecord:
    """What uacell knows about one session beyond what asyncua keeps."""

    connected: ua.DateTime = field(default_factory=ua.DateTime.now)
    last_contact: ua.DateTime = field(default_factory=ua.DateTime.now)
    session_name: str = ""
    endpoint_url: str = ""
    locale_ids: list[str] = field(default_factory=list)
    max_response_size: int = 0
    security_mode: ua.MessageSecurityMode = ua.MessageSecurityMode.None_
    security_policy_uri: str = ""
    client_certificate: bytes | None = None
    user_history: list[str] = field(default_factory=list)
    authentication: str = "None"
    counters: dict[str, list[int]] = field(default_factory=dict)  # field -> [total, errors]
    close_requested: bool = False


class Diagnostics:
    """The ServerDiagnostics of one server."""

    def __init__(self, app: Host, clock: Callable[[], float] = time.monotonic) -> None:
        self.app = app
        self.summary = ua.ServerDiagnosticsSummaryDataType()
        self.sessions: dict[str, SessionRecord] = {}
        self._written: dict[ua.NodeId, Any] = {}
        self._task: asyncio.Task[None] | None = None
        self._dirty = asyncio.Event()
        self._clock = clock

    @property
    def iserver(self) -> Any:
        return self.app.server.iserver

    # life cycle -------------------------------------------------------------------------------------

    async def start(self) -> None:
        await self._write(ENABLED_FLAG, ua.Variant(True, ua.VariantType.Boolean))
        await self.refresh()
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None

    async def _run(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._dirty.wait(), REFRESH_SECONDS)
            self._dirty.clear()
            try:
                await self.refresh()
            except Exception:
                log.exception("refreshing server diagnostics failed")

    # what happens ----------------------------------------------------------------------------------

    async def __call__(self, request: Request, call_next: Next) -> Any:
        """The diagnostics stage (``ua/pipeline.py``): one service request, counted for its session
        and the summary."""
        processor, typeid = request.processor, request.typeid
        session = getattr(processor, "session", None)
        if typeid == _CLOSE_SESSION and session is not None:
            self.record(session).close_requested = True
        try:
            result = await call_next(request)
        except (ServiceError, ua.UaStatusCodeError) as exc:
            self._count(processor, typeid, ok=False, code=exc.code)
            raise
        self._count(processor, typeid, ok=True, code=ua.StatusCodes.Good)
        return result

    def _count(self, processor: UaProcessor, typeid: ua.NodeId, *, ok: bool, code: int) -> None:
        s = self.summary
        if not ok:
            s.RejectedRequestsCount += 1
            if code in _SECURITY_CODES:
                s.SecurityRejectedRequestsCount += 1
            if typeid in (_CREATE_SESSION, _ACTIVATE_SESSION):
                s.RejectedSessionCount += 1
                if code in _SECURITY_CODES:
                    s.SecurityRejectedSessionCount += 1
        elif typeid == _CREATE_SUBSCRIPTION:
            s.CumulatedSubscriptionCount += 1
        session = getattr(processor, "session", None)
        record = self.sessions.get(_key(session)) if session is not None else None
        if record is not None:
            record.last_contact = ua.DateTime.now()
            for name in ("TotalRequestCount", _BY_TYPEID.get(typeid)):
                if name is None:
                    continue
                counter = record.counters.setdefault(name, [0, 0])
                counter[0] += 1
                counter[1] += 0 if ok else 1
            if typeid == _ACTIVATE_SESSION and ok:
                user = getattr(session, "user", None)
                record.authentication = getattr(user, "mechanism", "Anonymous")
                name = getattr(user, "name", None) or ""
                if not record.user_history or record.user_history[-1] != name:
                    record.user_history.append(name)
        if not ok or typeid in _AT_ONCE:
            self._dirty.set()

    def record(self, session: InternalSession) -> SessionRecord:
        return self.sessions.setdefault(_key(session), SessionRecord())

    def session_created(
        self, session: InternalSession, params: ua.CreateSessionParameters, processor: UaProcessor | None
    ) -> None:
        self.summary.CumulatedSessionCount += 1
        record = self.record(session)
        record.session_name = params.SessionName or ""
        record.endpoint_url = params.EndpointUrl or ""
        record.locale_ids = []
        record.max_response_size = int(params.MaxResponseMessageSize or 0)
        record.client_certificate = params.ClientCertificate or None
        connection = door_connection.connection(processor)
        policy = getattr(connection, "security_policy", None)
        if policy is not None:
            record.security_mode = policy.Mode
            record.security_policy_uri = str(getattr(policy, "URI", ""))
        self._dirty.set()

    def session_closed(self, session: InternalSession) -> None:
        record = self.sessions.pop(_key(session), None)
        if record is not None and not record.close_requested:
            timeout = float(getattr(session, "session_timeout", 0) or 0)
            idle = time.monotonic() - door_connection.last_activity(session, time.monotonic())
            if timeout and idle >= timeout:
                self.summary.SessionTimeoutCount += 1
            else:
                self.summary.SessionAbortCount += 1
        self._dirty.set()

    # publishing -------------------------------------------------------------------------------------

    def _live_sessions(self) -> list[InternalSession]:
        return [s for s in door_connection.external_sessions(self.iserver) if str(s.session_id) in self.sessions]

    def snapshot(self) -> tuple[ua.ServerDiagnosticsSummaryDataType, list[Any], list[Any]]:
        subscriptions = list(self.iserver.subscription_service.subscriptions.values())
        summary = ua.ServerDiagnosticsSummaryDataType(
            **{f.name: getattr(self.summary, f.name) for f in fields(self.summary)}
        )
        summary.CurrentSessionCount = door_connection.session_count(self.iserver)
        summary.CurrentSubscriptionCount = len(subscriptions)
        summary.PublishingIntervalCount = len({s.data.RevisedPublishingInterval for s in subscriptions})
        details, security = [], []
        for session in self._live_sessions():
            record = self.sessions[str(session.session_id)]
            mine = [s for s in subscriptions if s.session_id == session.session_id]
            details.append(self._details(session, record, mine))
            security.append(self._security(session, record))
        return summary, details, security

    def _details(
        self, session: InternalSession, record: SessionRecord, subs: list[Any]
    ) -> ua.SessionDiagnosticsDataType:
        d = ua.SessionDiagnosticsDataType()
        d.SessionId = session.session_id
        d.SessionName = record.session_name
        d.ClientDescription = getattr(session, "client_description", None) or ua.ApplicationDescription()
        d.ServerUri = self.app.server.get_application_uri()
        d.EndpointUrl = record.endpoint_url
        d.LocaleIds = list(record.locale_ids)
        d.ActualSessionTimeout = float(getattr(session, "session_timeout", 0) or 0) * 1000.0
        d.MaxResponseMessageSize = record.max_response_size
        d.ClientConnectionTime = record.connected
        d.ClientLastContactTime = record.last_contact
        d.CurrentSubscriptionsCount = len(subs)
        d.CurrentMonitoredItemsCount = sum(len(s.monitored_item_srv._monitored_items) for s in subs)
        d.CurrentPublishRequestsInQueue = 0
        d.UnauthorizedRequestCount = 0
        for name in ("TotalRequestCount", *_SERVICES.values()):
            total, errors = record.counters.get(name, (0, 0))
            setattr(d, name, ua.ServiceCounterDataType(TotalCount=total, ErrorCount=errors))
        return d

    def _security(self, session: InternalSession, record: SessionRecord) -> SessionSecurityDiagnosticsDataType:
        user = getattr(session, "user", None)
        d = SessionSecurityDiagnosticsDataType()
        d.SessionId = session.session_id
        d.ClientUserIdOfSession = getattr(user, "name", None) or ""
        d.ClientUserIdHistory = list(record.user_history)
        d.AuthenticationMechanism = record.authentication
        d.TransportEncoding = "UA Binary"
        d.TransportProtocol = "opc.tcp"
        d.SecurityMode = record.security_mode
        d.SecurityPolicyUri = record.security_policy_uri
        d.ClientCertificate = record.client_certificate
        return d

    async def refresh(self) -> None:
        summary, details, security = self.snapshot()
        await self._write(SUMMARY, ua.Variant(summary, ua.VariantType.ExtensionObject))
        for f in fields(summary):
            node_id = getattr(_O, f"Server_ServerDiagnostics_ServerDiagnosticsSummary_{f.name}", None)
            if node_id is not None:
                await self._write(ua.NodeId(node_id), ua.Variant(getattr(summary, f.name), ua.VariantType.UInt32))
        await self._write(SESSIONS, ua.Variant(details, ua.VariantType.ExtensionObject, is_array=True))
        await self._write(SECURITY, ua.Variant(security, ua.VariantType.ExtensionObject, is_array=True))

    async def _write(self, node: ua.NodeId, value: ua.Variant) -> None:
        if self._written.get(node) == value:
            return
        self._written[node] = value
        await self.iserver.aspace.write_attribute_value(node, ua.AttributeIds.Value, ua.DataValue(value))


def bind_subscription_methods(app: Host) -> None:
    """The Server object's methods on a subscription of the calling session (OPC 10000-5, 9.1 and 9.3):
    ``GetMonitoredItems(SubscriptionId) -> ServerHandles, ClientHandles`` and ``ResendData(SubscriptionId)``,
    which queues the current value of each of its Reporting data items for the next Publish.
    Bad_SubscriptionIdInvalid for an unknown subscription, Bad_UserAccessDenied for another session's."""
    from uacell.core.errors import CallError
    from uacell.core.roles import Family
    from uacell.ua.context import Caller, session_text
    from uacell.ua.door.subscriptions import send_current_values

    service = app.server.iserver.subscription_service

    def own(caller: Caller, subscription_id: int) -> Any:
        subscription = service.subscriptions.get(subscription_id)
        if subscription is None:
            raise CallError("BadSubscriptionIdInvalid", f"no subscription {subscription_id}")
        if session_text(subscription.session_id) != caller.session_id:
            raise CallError("BadUserAccessDenied", f"subscription {subscription_id} belongs to another session")
        return subscription

    async def get_monitored_items(caller: Caller, subscription_id: int) -> list[Any]:
        items = sorted(own(caller, subscription_id).monitored_item_srv._monitored_items.items())
        return [[int(i) for i, _ in items], [int(m.client_handle or 0) for _, m in items]]

    async def resend_data(caller: Caller, subscription_id: int) -> None:
        await send_current_values(own(caller, subscription_id))

    server = ua.NodeId(_O.Server)
    app.dispatcher.bind(server, ua.NodeId(_O.Server_GetMonitoredItems), Family.SERVER, get_monitored_items)
    app.dispatcher.bind(server, ua.NodeId(_O.Server_ResendData), Family.SERVER, resend_data)


def readable_by(node: ua.NodeId, role: str) -> bool:
    """Session security diagnostics (user names, certificates) are for admins only."""
    return node != SECURITY or role == "admin"
