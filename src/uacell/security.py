"""Everything server-side about security: certificate, endpoints, trust list, logins, per-session rights.

``install_security(app)`` is called by ``UacellServer.setup()`` after ``Server.init()`` and before the
binders run. It

- makes or reuses the server certificate in ``<data_dir>/pki/own`` and offers Basic256Sha256,
  Aes128_Sha256_RsaOaep and Aes256_Sha256_RsaPss with Sign and SignAndEncrypt, plus None where the
  listening policy allows it;
- checks client certificates against ``pki/trusted`` (``uacell.pki.CertificateValidator``);
- accepts anonymous and user-name identity tokens, but a user name only with an encrypted password
  or over a SignAndEncrypt channel (``Bad_IdentityTokenRejected`` otherwise);
- slows down repeated login failures per client address (``uacell.users.LoginThrottle``);
- uses its own session class: writes need the ``write`` action of ``uacell.roles``, the client's
  ApplicationUri is kept for ``Caller.client``, and ``on_session_closed`` hooks run when a session
  closes or times out (locks are released there);
- answers UserExecutable, UserAccessLevel, UserWriteMask and the FileType ``UserWritable`` property
  per session role (a Read hook).

asyncua gives a session neither its secure channel nor its peer address, so the per-connection
processor is published in a context variable while it handles a request.
"""

from __future__ import annotations

import asyncio
import contextvars
import dataclasses
import functools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.server.internal_session import InternalSession, SessionState
from asyncua.server.uaprocessor import UaProcessor

from uacell.pki import CertificateValidator, PkiPaths, TrustList, ensure_server_certificate
from uacell.roles import Family, Role, may, may_call
from uacell.ua import context
from uacell.ua.access import user_access_level
from uacell.ua.context import caller_of
from uacell.ua.diagnostics import readable_by as diagnostics_readable_by
from uacell.users import LoginThrottle

if TYPE_CHECKING:
    from uacell.server import UacellServer

log = logging.getLogger(__name__)

_P = ua.SecurityPolicyType
# Most widely supported first: asyncua asks clients on a None channel to encrypt user-name tokens
# with the first SignAndEncrypt policy of this list.
SECURE_POLICIES: list[ua.SecurityPolicyType] = [
    _P.Basic256Sha256_SignAndEncrypt,
    _P.Aes256Sha256RsaPss_SignAndEncrypt,
    _P.Aes128Sha256RsaOaep_SignAndEncrypt,
    _P.Basic256Sha256_Sign,
    _P.Aes256Sha256RsaPss_Sign,
    _P.Aes128Sha256RsaOaep_Sign,
]

_ACTIVATE = ua.NodeId(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary)
_USER_WRITABLE = ua.QualifiedName("UserWritable", 0)
_A = ua.AttributeIds

# The UaProcessor (one per TCP connection) handling the current request.
_processor: contextvars.ContextVar[UaProcessor | None] = contextvars.ContextVar("uacell_processor", default=None)
# The user name an ActivateSession under way presents (for the audit trail of a refused login).
_login_name: contextvars.ContextVar[list[str] | None] = contextvars.ContextVar("uacell_login_name", default=None)


def _address(processor: UaProcessor | None) -> str:
    peer = getattr(processor, "name", None)
    if isinstance(peer, tuple) and peer:
        return str(peer[0])
    return str(peer or "unknown")


def _channel_mode(processor: UaProcessor | None) -> ua.MessageSecurityMode:
    if processor is None:
        return ua.MessageSecurityMode.None_
    return processor._connection.security_policy.Mode


async def prepare_certificate(server: Server, data_dir: Path, application_uri: str, hosts: list[str]) -> Path:
    """Make or reuse ``pki/own/cert.der`` + ``key.pem`` and load them into ``server``; returns the cert path."""
    cert, key = ensure_server_certificate(PkiPaths.in_data_dir(data_dir), application_uri, hosts)
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    return cert


class Security:
    """The security setup of one server (reachable from asyncua objects as ``iserver._uacell_security``)."""

    def __init__(self, app: UacellServer) -> None:
        self.app = app
        self.server: Server = app.server
        self.throttle = LoginThrottle()
        self.on_session_closed: list[Callable[[InternalSession], None]] = []
        self._address_locks: dict[str, asyncio.Lock] = {}
        self.trust_list: TrustList | None = None
        self.policies: list[ua.SecurityPolicyType] = []

    async def install(self) -> None:
        cfg = self.app.config.server
        policy = self.app.policy
        iserver = self.server.iserver
        iserver._uacell_security = self  # type: ignore[attr-defined]
        await prepare_certificate(self.server, self.app.data_dir, self.server.get_application_uri(), [cfg.host])
        self.trust_list = TrustList(PkiPaths.in_data_dir(self.app.data_dir), trust_on_first_use=cfg.trust_on_first_use)
        if cfg.trust_on_first_use:
            log.warning("trust_on_first_use is on: every new client certificate is trusted and kept in %s",
                        self.trust_list.paths.trusted)
        self.server.set_certificate_validator(CertificateValidator(self.trust_list))
        self.policies = list(SECURE_POLICIES) + ([_P.NoSecurity] if policy.none_security else [])
        self.server.set_security_policy(self.policies)
        # X509 user tokens are not mapped to users: offering them would log such users in as anonymous.
        self.server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        iserver.create_session = self._create_session  # type: ignore[method-assign]
        original_decrypt = iserver.decrypt_user_token

        def decrypt_user_token(isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
            holder = _login_name.get()
            if holder is not None:
                holder.append(str(token.UserName))
            self.refuse_plaintext(token)
            return original_decrypt(isession, token)

        iserver.decrypt_user_token = decrypt_user_token  # type: ignore[method-assign]
        _install_processor_hook()
        context.add_read_hook(_read_hook)
        log.info("security: endpoints %s; anonymous clients are %s", ", ".join(p.name for p in self.policies),
                 policy.anonymous_role.label)

    # sessions ------------------------------------------------------------------------------------

    def _create_session(self, name: Any, user: Any = None, external: bool = False) -> InternalSession:
        iserver = self.server.iserver
        if user is None:
            return UacellSession(self, iserver, iserver.aspace, iserver.subscription_service, name, external=external)
        return UacellSession(self, iserver, iserver.aspace, iserver.subscription_service, name, user=user,
                             external=external)

    def session_closed(self, session: InternalSession) -> None:
        for hook in self.on_session_closed:
            try:
                hook(session)
            except Exception:
                log.exception("session-closed hook failed")

    # logins --------------------------------------------------------------------------------------

    def refuse_plaintext(self, token: ua.UserNameIdentityToken) -> None:
        """A password travels in clear text unless the token or the channel is encrypted: refuse that."""
        processor = _processor.get()
        if token.EncryptionAlgorithm or _channel_mode(processor) == ua.MessageSecurityMode.SignAndEncrypt:
            return
        log.info("refused login of user %r from %s: clear-text password on an unencrypted channel",
                    token.UserName, _address(processor))
        raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)

    def _address_lock(self, address: str) -> asyncio.Lock:
        return self._address_locks.setdefault(address, asyncio.Lock())

    async def activate(self, processor: UaProcessor, call: Callable[[], Any]) -> Any:
        """Run one ActivateSession: wait out the address's penalty, then record success or failure."""
        address = _address(processor)
        # One attempt at a time per address, so parallel connections cannot skip the delay.
        async with self._address_lock(address):
            wait = self.throttle.wait_time(address)
            if wait > 0:
                log.info("delaying login from %s by %.1f s after failed attempts", address, wait)
                await asyncio.sleep(wait)
            names: list[str] = []
            token = _login_name.set(names)
            try:
                result = await call()
            except ServiceError as exc:
                if exc.code == ua.StatusCodes.BadUserAccessDenied:
                    self.throttle.failed(address)
                self._audit_login(processor, address, names, ua.StatusCode(exc.code).name)
                raise
            finally:
                _login_name.reset(token)
            user = getattr(processor.session, "user", None)
            if user is not None and not getattr(user, "anonymous", True):
                self.throttle.succeeded(address)
            self._audit_login(processor, address, names, "Good")
            return result

    def _audit_login(self, processor: UaProcessor, address: str, names: list[str], result: str) -> None:
        from uacell.ua.observers import session_fields

        fields = session_fields(processor.session) if processor.session is not None else {}
        fields["user"] = names[-1] if names else fields.get("user", "anonymous")
        self.app.audit.record("login", **fields, address=address, result=result)

    # per-session attributes ------------------------------------------------------------------------

    def adjust_read(self, session: InternalSession, params: ua.ReadParameters, results: list[ua.DataValue]) -> None:
        role = caller_of(session).role
        aspace = self.server.iserver.aspace
        for i, (rv, dv) in enumerate(zip(params.NodesToRead, results, strict=False)):
            if dv.StatusCode is not None and not dv.StatusCode.is_good():
                continue
            attr = rv.AttributeId
            if attr == _A.Value and not diagnostics_readable_by(rv.NodeId, role):
                results[i] = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadUserAccessDenied))
                continue
            if attr == _A.UserExecutable:
                allowed = self.app.dispatcher.user_executable(rv.NodeId, role)
                if allowed is not None:
                    results[i] = _with_value(dv, allowed, ua.VariantType.Boolean)
            elif attr == _A.UserAccessLevel and dv.Value is not None and isinstance(dv.Value.Value, int):
                needed = self.app.writes.required_role(rv.NodeId)
                level = user_access_level(role, dv.Value.Value, needed)
                results[i] = _with_value(dv, level, ua.VariantType.Byte)
            elif attr == _A.UserWriteMask and not may(Role.parse(role), "write"):
                results[i] = _with_value(dv, 0, ua.VariantType.UInt32)
            elif attr == _A.Value and dv.Value is not None and isinstance(dv.Value.Value, bool):
                node = aspace.get(rv.NodeId)
                name = node.attributes.get(_A.BrowseName) if node is not None else None
                if name is not None and name.value.Value.Value == _USER_WRITABLE:
                    allowed = dv.Value.Value and may_call(Role.parse(role), "Write", Family.FILE)
                    results[i] = _with_value(dv, allowed, ua.VariantType.Boolean)


def _with_value(dv: ua.DataValue, value: Any, vtype: ua.VariantType) -> ua.DataValue:
    return dataclasses.replace(dv, Value=ua.Variant(value, vtype))


def _read_hook(session: InternalSession, params: Any, results: list) -> None:
    security = getattr(session.iserver, "_uacell_security", None)
    if security is not None:
        security.adjust_read(session, params, results)


class UacellSession(InternalSession):
    """A session that checks writes against the role table and reports its end."""

    def __init__(self, security: Security, *args: Any, **kwargs: Any) -> None:
        self._security = security
        self._client_description: ua.ApplicationDescription | None = None
        self.client_address = ""
        super().__init__(*args, **kwargs)

    async def create_session(self, params: ua.CreateSessionParameters, sockname=None) -> ua.CreateSessionResult:
        self._client_description = params.ClientDescription  # Caller.client: LockingClient shows it
        processor = _processor.get()
        self.client_address = _address(processor)
        if _channel_mode(processor) == ua.MessageSecurityMode.None_:
            # OPC 10000-4 CreateSession: on a SecurityPolicy None channel the client certificate plays
            # no part (nothing is signed with it), so it is not checked against the trust list.
            params = dataclasses.replace(params, ClientCertificate=None)
        result = await super().create_session(params, sockname=sockname)
        self._audit("session_open")
        diagnostics = self._security.app.diagnostics
        if diagnostics is not None:
            diagnostics.session_created(self, params, processor)
        return result

    def _audit(self, event: str) -> None:
        from uacell.ua.observers import session_fields

        self._security.app.audit.record(event, **session_fields(self), address=self.client_address)

    async def write(self, params: ua.WriteParameters) -> list[ua.StatusCode]:
        return await self._security.app.writes.write(caller_of(self), params, super().write)

    async def close_session(self, delete_subs: bool = True) -> None:
        already = self.state == SessionState.Closed
        await super().close_session(delete_subs)
        if not already:
            self._audit("session_close")
            if self._security.app.diagnostics is not None:
                self._security.app.diagnostics.session_closed(self)
            self._security.session_closed(self)


def _install_processor_hook() -> None:
    """Wrap UaProcessor._process_message once: publish the processor and the request's ReturnDiagnostics,
    throttle ActivateSession."""
    if getattr(UaProcessor, "_uacell_installed", False):
        return
    original = UaProcessor._process_message

    @functools.wraps(original)
    async def _process_message(self: UaProcessor, typeid, requesthdr, seqhdr, body):
        token = _processor.set(self)
        diagnostics = context.set_return_diagnostics(int(getattr(requesthdr, "ReturnDiagnostics", 0) or 0))
        try:
            security = getattr(self.iserver, "_uacell_security", None)
            server_diagnostics = getattr(self.iserver, "_uacell_diagnostics", None)

            async def serve() -> Any:
                if security is not None and typeid == _ACTIVATE:
                    return await security.activate(self, lambda: original(self, typeid, requesthdr, seqhdr, body))
                return await original(self, typeid, requesthdr, seqhdr, body)

            if server_diagnostics is not None:
                return await server_diagnostics.request(self, typeid, serve)
            return await serve()
        finally:
            context.reset_return_diagnostics(diagnostics)
            _processor.reset(token)

    UaProcessor._process_message = _process_message  # type: ignore[method-assign]
    UaProcessor._uacell_installed = True  # type: ignore[attr-defined]


async def install_security(app: UacellServer) -> Security:
    """Set up certificates, endpoints, trust list, login rules and per-session rights for ``app``."""
    security = Security(app)
    await security.install()
    return security
