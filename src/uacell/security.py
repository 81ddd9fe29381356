"""Everything server-side about security: certificate, endpoints, trust list, logins, per-session rights.

``install_security(app)`` is called by ``UacellServer.setup()`` after ``Server.init()`` and before the
binders run. It

- makes or reuses the server certificate in ``<data_dir>/pki/own`` and offers Basic256Sha256,
  Aes128_Sha256_RsaOaep and Aes256_Sha256_RsaPss with Sign and SignAndEncrypt, plus None where the
  listening policy allows it;
- checks client certificates against ``pki/trusted`` (``uacell.pki.CertificateValidator``);
- accepts anonymous and user-name identity tokens, but a user name only with an encrypted password
  or over a SignAndEncrypt channel (``Bad_IdentityTokenRejected`` otherwise);
- slows down repeated login failures per user name, at one address and across addresses
  (``uacell.users.LoginThrottle``), and checks passwords in worker threads, a few at a time;
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
from asyncua.ua.ua_binary import struct_from_binary

from uacell.pki import CertificateValidator, PkiPaths, TrustList, ensure_server_certificate
from uacell.roles import Family, Role, may, may_call
from uacell.ua import context
from uacell.ua.access import user_access_level, verified_login
from uacell.ua.context import caller_of
from uacell.ua.limits import LimitedSession
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
        limits = app.config.limits
        self.throttle = LoginThrottle(
            base=limits.login_base_delay,
            cap=limits.login_max_delay,
            free=limits.login_free_failures,
            free_per_user=limits.login_free_failures_per_user,
        )
        self.password_checks = asyncio.Semaphore(limits.password_checks)
        self.on_session_closed: list[Callable[[InternalSession], None]] = []
        self._user_locks: dict[str, asyncio.Lock] = {}
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
        log.warning("refused login of user %r from %s: clear-text password on an unencrypted channel",
                    token.UserName, _address(processor))
        raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)

    async def activate(self, processor: UaProcessor, requesthdr: Any, body: Any, call: Callable[[], Any]) -> Any:
        """Run one ActivateSession: throttled per user name (never for anonymous logins), the password
        checked in a worker thread, at most ``[limits] password_checks`` at once server-wide."""
        token = _identity_token(body)
        if not isinstance(token, ua.UserNameIdentityToken) or not token.UserName:
            return await call()  # anonymous or another token type: asyncua decides, nobody waits
        user, address = str(token.UserName), _address(processor)
        # One attempt at a time per user name, so parallel connections cannot skip the delay.
        lock = self._user_locks.setdefault(user, asyncio.Lock())
        try:
            async with lock:
                wait = self.throttle.wait_time(user, address)
                if wait > 0:
                    log.info("delaying login of user %r from %s by %.1f s after failed attempts", user, address, wait)
                    await asyncio.sleep(wait)
                verified = await self._verify_off_loop(processor, requesthdr, token)
                try:
                    result = await call()
                except ServiceError as exc:
                    if exc.code == ua.StatusCodes.BadUserAccessDenied:
                        self.throttle.failed(user, address)
                    raise
                finally:
                    if verified is not None:
                        verified_login.reset(verified)
                logged_in = getattr(processor.session, "user", None)
                if logged_in is not None and not getattr(logged_in, "anonymous", True):
                    self.throttle.succeeded(user, address)
                return result
        finally:
            if not lock.locked() and self._user_locks.get(user) is lock:
                del self._user_locks[user]  # a spray of names leaves nothing behind

    async def _verify_off_loop(self, processor: UaProcessor, requesthdr: Any, token: ua.UserNameIdentityToken) -> Any:
        """Check the password in a worker thread (the hash takes tens of ms) and leave the outcome for
        ``UacellUserManager.get_user``; None when asyncua's own path must decide (it refuses then)."""
        if not token.EncryptionAlgorithm and _channel_mode(processor) != ua.MessageSecurityMode.SignAndEncrypt:
            return None  # a clear-text password is refused before any check
        iserver = self.server.iserver
        isession = processor.session or iserver.lookup_external_session(requesthdr.AuthenticationToken)
        if isession is None:
            return None
        try:
            # asyncua's plain decryption (no side effects); the real activation decrypts again.
            name, password = type(iserver).decrypt_user_token(iserver, isession, token)
        except Exception:
            return None  # asyncua answers the malformed token itself
        async with self.password_checks:
            role = await asyncio.to_thread(self.app.users.verify, name, password or "")
        return verified_login.set((name, password or "", role))

    # per-session attributes ------------------------------------------------------------------------

    def adjust_read(self, session: InternalSession, params: ua.ReadParameters, results: list[ua.DataValue]) -> None:
        role = caller_of(session).role
        aspace = self.server.iserver.aspace
        for i, (rv, dv) in enumerate(zip(params.NodesToRead, results, strict=False)):
            if dv.StatusCode is not None and not dv.StatusCode.is_good():
                continue
            attr = rv.AttributeId
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


class UacellSession(LimitedSession):
    """A session that checks writes against the role table and reports its end."""

    def __init__(self, security: Security, *args: Any, **kwargs: Any) -> None:
        self._security = security
        self._client_description: ua.ApplicationDescription | None = None
        super().__init__(*args, **kwargs)

    async def create_session(self, params: ua.CreateSessionParameters, sockname=None) -> ua.CreateSessionResult:
        self._client_description = params.ClientDescription  # Caller.client: LockingClient shows it
        if _channel_mode(_processor.get()) == ua.MessageSecurityMode.None_:
            # OPC 10000-4 CreateSession: on a SecurityPolicy None channel the client certificate plays
            # no part (nothing is signed with it), so it is not checked against the trust list.
            params = dataclasses.replace(params, ClientCertificate=None)
        return await super().create_session(params, sockname=sockname)

    async def write(self, params: ua.WriteParameters) -> list[ua.StatusCode]:
        return await self._security.app.writes.write(caller_of(self), params, super().write)

    async def close_session(self, delete_subs: bool = True) -> None:
        already = self.state == SessionState.Closed
        await super().close_session(delete_subs)
        if not already:
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
            if security is not None and typeid == _ACTIVATE:
                return await security.activate(
                    self, requesthdr, body, lambda: original(self, typeid, requesthdr, seqhdr, body)
                )
            return await original(self, typeid, requesthdr, seqhdr, body)
        finally:
            context.reset_return_diagnostics(diagnostics)
            _processor.reset(token)

    UaProcessor._process_message = _process_message  # type: ignore[method-assign]
    UaProcessor._uacell_installed = True  # type: ignore[attr-defined]


def _identity_token(body: Any) -> Any:
    """The UserIdentityToken of an ActivateSession body, read without consuming it (None if unreadable)."""
    try:
        return struct_from_binary(ua.ActivateSessionParameters, body.copy()).UserIdentityToken
    except Exception:
        return None


async def install_security(app: UacellServer) -> Security:
    """Set up certificates, endpoints, trust list, login rules and per-session rights for ``app``."""
    security = Security(app)
    await security.install()
    return security
