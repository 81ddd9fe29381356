"""The Server's audit events of secure channels, sessions and refused certificates (OPC 10000-4 6.5.5 and
6.5.6, OPC 10000-5 6.4):
the server says it audits (``Server/Auditing`` is true), so every OpenSecureChannel (renewals of its
token aside), CloseSecureChannel, CreateSession, ActivateSession and end of a session fires its audit
event, refused or not, and a refused client certificate fires the AuditCertificate subtype its refusal
names, besides.

| Event type | SourceName | when |
| --- | --- | --- |
| AuditOpenSecureChannelEventType | ``SecureChannel/OpenSecureChannel`` | a secure channel opened or refused |
| AuditChannelEventType | ``SecureChannel/CloseSecureChannel`` | a client closes its secure channel |
| AuditCreateSessionEventType | ``Session/CreateSession`` | every CreateSession (SessionId null when refused) |
| AuditActivateSessionEventType | ``Session/ActivateSession`` | every ActivateSession, a change of user too |
| AuditSessionEventType | ``Session/CloseSession``, ``Session/Timeout``, ``Session/Terminated`` | a session ends |
| AuditCertificate...EventType | ``Security/Certificate`` | a client certificate refused at CreateSession, |
| | | or a user certificate at ActivateSession (decision 102) |

Their SourceNode is the Server object and they are fired through it. They carry user names, client
certificates and identity tokens (never a password), so they reach only sessions whose role is
``admin`` (decision 94), are not kept in history and are not published.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua
from asyncua.server.internal_session import InternalSession

from uacell.core.roles import Role
from uacell.security.chain import first_certificate
from uacell.security.pki import thumbprint
from uacell.ua import toolkit
from uacell.ua.context import audit_entry_id, caller_of
from uacell.ua.toolkit import EventEmitter

_O = ua.ObjectIds
_S = ua.StatusCodes
_VT = ua.VariantType
SERVER = ua.NodeId(_O.Server)

# Which AuditCertificate subtype a refusal fires (OPC 10000-5 6.4.13 to 6.4.19).
CERTIFICATE_EVENTS: Mapping[int, int] = {
    _S.BadCertificateTimeInvalid: _O.AuditCertificateExpiredEventType,
    _S.BadCertificateIssuerTimeInvalid: _O.AuditCertificateExpiredEventType,
    _S.BadCertificateUriInvalid: _O.AuditCertificateDataMismatchEventType,
    _S.BadCertificateHostNameInvalid: _O.AuditCertificateDataMismatchEventType,
    _S.BadCertificateUntrusted: _O.AuditCertificateUntrustedEventType,
    _S.BadCertificateChainIncomplete: _O.AuditCertificateUntrustedEventType,
    _S.BadCertificateRevoked: _O.AuditCertificateRevokedEventType,
    _S.BadCertificateIssuerRevoked: _O.AuditCertificateRevokedEventType,
    _S.BadCertificateRevocationUnknown: _O.AuditCertificateRevokedEventType,
    _S.BadCertificateIssuerRevocationUnknown: _O.AuditCertificateRevokedEventType,
    _S.BadCertificateUseNotAllowed: _O.AuditCertificateMismatchEventType,
    _S.BadCertificateIssuerUseNotAllowed: _O.AuditCertificateMismatchEventType,
}
SESSION_EVENTS = (_O.AuditCreateSessionEventType, _O.AuditActivateSessionEventType, _O.AuditSessionEventType)
CHANNEL_EVENTS = (_O.AuditOpenSecureChannelEventType, _O.AuditChannelEventType)


@dataclass(frozen=True)
class ChannelRequest:
    """What an OpenSecureChannel asked for, as its audit event reports it."""

    certificate: bytes | None  # as the client sent it: its certificate, or its chain
    policy_uri: str
    mode: ua.MessageSecurityMode
    request_type: ua.SecurityTokenRequestType
    requested_lifetime: float  # ms


class SecurityAuditEvents:
    """Fires the audit events of the table above for one server."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self._emitters: dict[int, EventEmitter] = {}
        # the sessions that were admin when they last activated; their role is checked again at each event
        # (a user certificate's expiry makes a session anonymous), the others are never looked at
        self._admins: weakref.WeakValueDictionary[ua.NodeId, InternalSession] = weakref.WeakValueDictionary()

    async def install(self) -> None:
        for type_id in {
            *CHANNEL_EVENTS,
            *SESSION_EVENTS,
            _O.AuditCertificateInvalidEventType,
            *CERTIFICATE_EVENTS.values(),
        }:
            self._emitters[type_id] = await EventEmitter.create(self.server, type_id, SERVER)

    # the service calls ------------------------------------------------------------------------------

    async def channel_opened(self, request: ChannelRequest, channel_id: str, code: int, why: str = "") -> None:
        """An OpenSecureChannel answered ``code`` (``channel_id`` empty when refused)."""
        leaf = first_certificate(request.certificate) if request.certificate else None
        fields = {
            "SecureChannelId": (channel_id, _VT.String),
            "ClientCertificate": (request.certificate, _VT.ByteString),
            "ClientCertificateThumbprint": (_thumbprint(leaf), _VT.String),
            "RequestType": (request.request_type, _VT.Int32),
            "SecurityPolicyUri": (request.policy_uri, _VT.String),
            "SecurityMode": (request.mode, _VT.Int32),
            "RequestedLifetime": (request.requested_lifetime, _VT.Double),
        }
        good = ua.StatusCode(code).is_good()
        mode = request.mode.name if isinstance(request.mode, ua.MessageSecurityMode) else str(request.mode)
        renewal = request.request_type == ua.SecurityTokenRequestType.Renew
        if good:
            message = f"secure channel {channel_id} {'renewed' if renewal else 'opened'} ({mode})"
        elif renewal:
            message = f"secure channel {channel_id} refused its renewal: {why}"
        else:
            message = f"secure channel refused: {why}"
        # OPC 10000-5 6.4.6: the ClientUserId "shall be set to System/OpenSecureChannel"
        opened = _O.AuditOpenSecureChannelEventType
        await self._fire(opened, "SecureChannel/OpenSecureChannel", fields, code, "System/OpenSecureChannel", message)

    async def channel_closed(self, channel_id: str) -> None:
        """A client's CloseSecureChannel."""
        fields = {"SecureChannelId": (channel_id, _VT.String)}
        closed = _O.AuditChannelEventType
        await self._fire(
            closed, "SecureChannel/CloseSecureChannel", fields, _S.Good, None, f"secure channel {channel_id} closed"
        )

    async def session_created(
        self,
        session: InternalSession,
        params: ua.CreateSessionParameters,
        channel_id: str,
        code: int,
        why: str = "",
    ) -> None:
        """A CreateSession answered ``code`` (its session's id null when refused)."""
        good = ua.StatusCode(code).is_good()
        der = params.ClientCertificate or None
        fields = {
            "SessionId": (session.session_id if good else ua.NodeId(), _VT.NodeId),
            "SecureChannelId": (channel_id, _VT.String),
            "ClientCertificate": (der, _VT.ByteString),
            "ClientCertificateThumbprint": (_thumbprint(der), _VT.String),
            "RevisedSessionTimeout": (float(getattr(session, "session_timeout", 0) or 0) * 1000.0, _VT.Double),
        }
        name = params.SessionName or ""
        message = f"session {name!r} created" if good else f"session {name!r} refused: {why or _name(code)}"
        await self._fire(
            _O.AuditCreateSessionEventType, "Session/CreateSession", fields, code, "System/CreateSession", message
        )

    async def session_activated(
        self, session: InternalSession | None, channel_id: str, token: Any, user: str | None, code: int
    ) -> None:
        """An ActivateSession (a change of user too) answered ``code``."""
        fields = {
            "SessionId": (session.session_id if session is not None else ua.NodeId(), _VT.NodeId),
            "SecureChannelId": (channel_id, _VT.String),
            "ClientSoftwareCertificates": ([], _VT.ExtensionObject),
            "UserIdentityToken": (reported_token(token), _VT.ExtensionObject),
        }
        who = user or "anonymous"
        good = ua.StatusCode(code).is_good()
        if session is not None and good:
            if _is_admin(session):
                self._admins[session.session_id] = session
            else:
                self._admins.pop(session.session_id, None)
        message = f"session activated for {who}" if good else f"activation for {who} refused ({_name(code)})"
        await self._fire(_O.AuditActivateSessionEventType, "Session/ActivateSession", fields, code, user, message)

    async def session_closed(self, session: InternalSession, cause: str) -> None:
        """A session ended: ``cause`` is CloseSession, Timeout or Terminated (OPC 10000-4 6.5.6)."""
        fields = {"SessionId": (session.session_id, _VT.NodeId)}
        user = caller_of(session).user
        await self._fire(
            _O.AuditSessionEventType, f"Session/{cause}", fields, _S.Good, user, f"session ended ({cause})"
        )
        self._admins.pop(session.session_id, None)

    async def certificate_refused(self, code: int, der: bytes | None, why: str, uri: str | None = None) -> None:
        """A client certificate refused with ``code`` (the precise one, not what the client was told);
        ``uri``: the ApplicationUri the client gave."""
        type_id = CERTIFICATE_EVENTS.get(code, _O.AuditCertificateInvalidEventType)
        fields: dict[str, tuple[Any, ua.VariantType]] = {"Certificate": (der, _VT.ByteString)}
        if type_id == _O.AuditCertificateDataMismatchEventType:  # the one that was found not to match
            fields["InvalidUri"] = (uri if code == _S.BadCertificateUriInvalid else None, _VT.String)
            fields["InvalidHostname"] = (None, _VT.String)
        await self._fire(type_id, "Security/Certificate", fields, code, None, f"{why} ({_name(code)})")

    # delivery ------------------------------------------------------------------------------------------

    def audience(self) -> list[int]:
        """The subscriptions that may receive these events: those of sessions whose role is admin."""
        admins = {sid for sid, session in list(self._admins.items()) if _is_admin(session)}
        if not admins:
            return []
        subscriptions = self.server.iserver.subscription_service.subscriptions
        return [sid for sid, sub in subscriptions.items() if sub.session_id in admins]

    async def _fire(
        self,
        type_id: int,
        source_name: str,
        fields: dict[str, tuple[Any, ua.VariantType]],
        code: int,
        client_user_id: str | None,
        message: str,
    ) -> None:
        good = ua.StatusCode(code).is_good()
        now = datetime.now(UTC)
        fields = {
            **fields,
            "ActionTimeStamp": (now, _VT.DateTime),
            "Status": (good, _VT.Boolean),
            "ServerId": (self.server.get_application_uri(), _VT.String),
            "ClientAuditEntryId": (audit_entry_id() or None, _VT.String),
            "ClientUserId": (client_user_id, _VT.String),
            "StatusCodeId": (ua.StatusCode(code), _VT.StatusCode),
        }
        await self._emitters[type_id].fire(
            (SERVER,),
            fields,
            to=self.audience(),
            EventId=ua.Variant(toolkit.new_event_id(), _VT.ByteString),
            Time=now,
            ReceiveTime=now,
            Severity=100 if good else 500,
            SourceNode=SERVER,
            SourceName=source_name,
            Message=ua.LocalizedText(message),
        )


def _is_admin(session: InternalSession) -> bool:
    return Role.parse(caller_of(session).role) >= Role.ADMIN


def reported_token(token: Any) -> Any:
    """The identity token as an audit event reports it (OPC 10000-5 6.4.10): a user name without its
    password, a certificate token without its signature, an anonymous token; None for anything else."""
    if isinstance(token, ua.UserNameIdentityToken):
        return ua.UserNameIdentityToken(PolicyId=token.PolicyId, UserName=token.UserName)
    if isinstance(token, ua.X509IdentityToken):
        return ua.X509IdentityToken(PolicyId=token.PolicyId, CertificateData=token.CertificateData)
    if isinstance(token, ua.AnonymousIdentityToken):
        return ua.AnonymousIdentityToken(PolicyId=token.PolicyId)
    return None


def _thumbprint(der: bytes | None) -> str | None:
    return thumbprint(der) if der else None


def _name(code: int) -> str:
    return str(ua.StatusCode(code).name)
