"""Everything server-side about security: certificate, endpoints, trust list, logins, per-session rights.

``install_security(app)`` is called by ``UacellServer.setup()`` after ``Server.init()`` and before the
binders run. It

- makes or reuses the server certificate in ``<data_dir>/pki/own`` and offers Basic256Sha256,
  Aes128_Sha256_RsaOaep and Aes256_Sha256_RsaPss with Sign and SignAndEncrypt, plus None where the
  listening policy allows it;
- accepts exactly the security policies and modes of the endpoints it offers: an OpenSecureChannel
  asking for another is answered with an Error message (Bad_SecurityPolicyRejected or
  Bad_SecurityModeRejected) and the connection closed. The one exception is policy None where it is
  not offered: such a channel serves discovery only (GetEndpoints, FindServers; OPC 10000-4 wants
  discovery reachable without security) and every other request on it, CreateSession and
  ActivateSession included, answers Bad_SecurityPolicyRejected. Refusals are logged once per client
  address, reason and interval (``RefusalLog``);
- checks client certificates, with the issuers they were sent with, at CreateSession against ``pki/trusted``,
  ``pki/issuers`` and ``pki/crl`` (``uacell.security.pki.CertificateValidator``, decision 92);
- accepts anonymous, user-name and X.509 identity tokens, but a user name only with an encrypted password
  or over a SignAndEncrypt channel (``Bad_IdentityTokenRejected`` otherwise); an encrypted password
  must use the algorithm of the endpoint's user token policy and carry the last server nonce this
  session was sent (``Bad_IdentityTokenInvalid`` otherwise), so a captured token cannot be replayed;
- accepts X.509 user certificates bound to users, signed for this session's nonce
  (``uacell.security.certificate_login``, decision 84);
- gives sessions random AuthenticationTokens and lets a session move to another secure channel only
  when activated, from the same client certificate and with the same identity;
- slows down repeated login failures per user name, at one address and across addresses
  (``uacell.security.users.LoginThrottle``), and checks passwords in worker threads, a few at a time;
- uses its own session class: writes need the ``write`` action of ``uacell.core.roles``, the client's
  ApplicationUri is kept for ``Caller.client``, and ``on_session_closed`` hooks run when a session
  closes or times out (locks are released there);
- answers UserExecutable, UserAccessLevel, UserWriteMask and the FileType ``UserWritable`` property
  per session role (a Read hook).

asyncua gives a session neither its secure channel nor its peer address, so the per-connection
processor is published in a context variable while it handles a request.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import hmac
import logging
import os
import struct
import time
import weakref
from collections.abc import Awaitable, Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, cast
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.common.utils import Buffer, ServiceError, create_nonce
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SECURITY_POLICY_TYPE_MAP, SecurityPolicyNone
from asyncua.server.internal_session import InternalSession, SessionState
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary
from cryptography import x509
from cryptography.exceptions import InvalidSignature

from uacell.config import login_answer_margin
from uacell.core.background import stop_task
from uacell.core.logs import RefusalLog
from uacell.core.roles import Family, Role, may
from uacell.security.access import user_access_level, verified_login
from uacell.security.audit_events import ChannelRequest, SecurityAuditEvents
from uacell.security.certificate_login import (
    TokenRefused,
    VerifiedCertificate,
    check_user_certificate,
)
from uacell.security.chain import (
    Anchors,
    Refusal,
    check_chain,
    der_of,
    first_certificate,
    next_change,
    split_chain,
)
from uacell.security.own_certificate import finish_install, own_issuers
from uacell.security.pki import (
    CertificateValidator,
    PkiPaths,
    RejectedLimit,
    TrustList,
    ensure_server_certificate,
    load_server_key,
    read_anchors,
    told,
    trust_stamp,
)
from uacell.security.pki import thumbprint as app_thumbprint  # SHA-1, OPC UA's; users' is SHA-256
from uacell.security.trust_list_file import finish_update
from uacell.security.users import LoginThrottle, thumbprint
from uacell.services.diagnostics import readable_by as diagnostics_readable_by
from uacell.ua import channel, context, door
from uacell.ua.context import UacellUser, caller_of
from uacell.ua.door.certificate import send_with_chain
from uacell.ua.door.connection import (
    channel_id,
    channel_open,
    connection,
    external_sessions,
    last_activity,
    sent_certificate,
)
from uacell.ua.door.connection import close as close_channel
from uacell.ua.limits import LimitedSession, check_operations
from uacell.ua.pipeline import Next, Request

if TYPE_CHECKING:
    from uacell.host import Host

log = logging.getLogger(__name__)

USERS_WATCH_INTERVAL = 1.0  # seconds between two looks at users.toml (decision 99)
TRUST_WATCH_INTERVAL = 1.0  # seconds between two looks at the trust list's folders (decision 100)

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
# What a SecurityPolicy None channel may ask where None is not an offered endpoint.
_DISCOVERY = {
    ua.NodeId(i)
    for i in (
        ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary,
        ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary,
        ua.ObjectIds.FindServersOnNetworkRequest_Encoding_DefaultBinary,
        ua.ObjectIds.CloseSecureChannelRequest_Encoding_DefaultBinary,
    )
}
_S = ua.StatusCodes
# The asymmetric encryption algorithm each security policy names (OPC 10000-7), for user token secrets.
_TOKEN_ALGORITHM: dict[str, str] = {
    cast(Any, cls).URI: cast(Any, cls).AsymmetricEncryptionURI for cls, _, _ in SECURITY_POLICY_TYPE_MAP.values()
}
_DECRYPT: dict[str, Callable[[Any, bytes], bytes]] = {
    "http://www.w3.org/2001/04/xmlenc#rsa-1_5": uacrypto.decrypt_rsa15,
    "http://www.w3.org/2001/04/xmlenc#rsa-oaep": uacrypto.decrypt_rsa_oaep,
    "http://opcfoundation.org/UA/security/rsa-oaep-sha2-256": uacrypto.decrypt_rsa_oaep_sha256,
}
_USER_WRITABLE = ua.QualifiedName("UserWritable", 0)
_A = ua.AttributeIds

# The UaProcessor (one per TCP connection) handling the current request.
# The user name an ActivateSession under way presents (for the audit trail of a refused login).


_address = channel.peer_address
_channel_policy = channel.channel_policy


def _channel_mode(processor: UaProcessor | None) -> ua.MessageSecurityMode:
    return channel.channel_policy(processor)[1]


def open_token_secret(plain: bytes, nonce: bytes | None) -> bytes:
    """The password inside a decrypted user token secret (OPC 10000-4, 7.41: a UInt32 length, then the
    password, then the server nonce). Raises ValueError unless the secret ends with ``nonce``."""
    if not nonce:
        raise ValueError("this session has no server nonce to check against")
    if len(plain) < 4:
        raise ValueError("secret too short")
    (length,) = struct.unpack_from("<I", plain)
    if length < len(nonce) or 4 + length > len(plain):
        raise ValueError("secret length out of range")
    secret = plain[4 : 4 + length]
    if not hmac.compare_digest(secret[len(secret) - len(nonce) :], nonce):
        raise ValueError("the server nonce in the token is not the one this session was sent")
    return secret[: len(secret) - len(nonce)]


def _drop_fault_echo(record: logging.LogRecord) -> bool:
    """asyncua logs every ServiceFault it sends at ERROR; uacell logs its refusals itself (rate-limited)."""
    return not str(record.msg).startswith("sending service fault response")


class _ChannelRefused(Exception):
    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


async def prepare_certificate(server: Server, data_dir: Path, application_uri: str, hosts: list[str]) -> Path:
    """Make or reuse ``pki/own/cert.der`` + ``key.pem`` and load them into ``server``; returns the cert path."""
    paths = PkiPaths.in_data_dir(data_dir)
    if finish_install(paths):  # a `uacell cert install` with a new key that a crash cut short
        log.warning("the server certificate installed last is now used with its key (the install had not finished)")
    if finish_update(paths):  # a CloseAndUpdate of the trust list that a crash cut short
        log.warning("the trust list written last by CloseAndUpdate is now in place (the replacement had not finished)")
    cert, _ = ensure_server_certificate(paths, application_uri, hosts)
    own = x509.load_der_x509_certificate(cert.read_bytes())
    # what asyncua's load_certificate and load_private_key set, without a thread per file, and the
    # key's consistency checked once per key (pki.load_server_key)
    door.configure(server.iserver, "InternalServer.certificate", own)
    door.configure(server.iserver, "InternalServer.private_key", load_server_key(paths))
    issuers = own_issuers(paths, own)
    if issuers:
        send_with_chain(server, b"".join(der_of(c) for c in issuers))
        log.info("the server certificate is sent with %d certificate(s) of its CA (%s)", len(issuers), paths.chain)
    return cert


class _Logins:
    """The login part of ``Security``: ActivateSession with a user name throttled per user name,
    answered before its deadline (decision 65), the password checked in a worker thread and every
    attempt audited."""

    app: Host
    server: Server
    throttle: LoginThrottle
    password_checks: asyncio.Semaphore
    _password_threads: ThreadPoolExecutor
    _user_locks: dict[str, asyncio.Lock]
    _lock_users: dict[str, int]  # attempts holding or waiting for each user name's lock
    audit_events: SecurityAuditEvents
    refusals: RefusalLog
    _refused_user_certificates: weakref.WeakKeyDictionary[InternalSession, tuple[int, bytes, str]]

    def decrypt_user_token(self, isession: InternalSession, token: ua.UserNameIdentityToken) -> tuple[str, str]:
        raise NotImplementedError  # Security's

    async def activate(self, processor: UaProcessor, requesthdr: Any, body: Any, call: Callable[[], Any]) -> Any:
        """Run one ActivateSession: throttled per user name (never for anonymous logins), the password
        checked in a worker thread, at most ``[limits] password_checks`` at once server-wide."""
        session = processor.session
        if session is not None and (session.state == SessionState.Closed or session.nonce is None):
            raise ServiceError(_S.BadSessionIdInvalid)  # its CreateSession was refused
        token = _identity_token(body)
        address = _address(processor)
        if isinstance(token, ua.X509IdentityToken):
            # No secret to guess (the signature proves the key): nobody waits (decision 84).
            return await self._audited(processor, address, self.certificate_user(token), call, token)
        if not isinstance(token, ua.UserNameIdentityToken) or not token.UserName:
            # Anonymous or another token type: asyncua decides, nobody waits.
            return await self._audited(processor, address, None, call, token)
        user = str(token.UserName)
        deadline = self.answer_deadline(processor, requesthdr)
        # One attempt at a time per user name, so parallel connections cannot skip the delay.
        lock = self._user_locks.setdefault(user, asyncio.Lock())
        self._lock_users[user] = self._lock_users.get(user, 0) + 1
        try:
            if not lock.locked():
                await lock.acquire()
            else:
                try:
                    await asyncio.wait_for(lock.acquire(), max(0.0, deadline - time.monotonic()))
                except TimeoutError:
                    await self._unchecked(
                        processor, address, user, token, "another attempt of this user name was under way"
                    )
            try:
                wait = self.throttle.wait_time(user, address)
                if wait > 0:
                    if time.monotonic() + wait > deadline:
                        why = f"its {wait:.1f} s delay would outlast its deadline"
                        await self._unchecked(processor, address, user, token, why)
                    log.info("delaying login of user %r from %s by %.1f s after failed attempts", user, address, wait)
                    await asyncio.sleep(wait)
                return await self._checked_login(processor, requesthdr, token, address, user, call)
            finally:
                lock.release()
        finally:
            # The last attempt of this name (none waiting for the lock either) forgets it: a spray of
            # names leaves nothing behind, and a waiter is never left with a lock nobody else shares.
            left = self._lock_users[user] - 1
            if left:
                self._lock_users[user] = left
            else:
                del self._lock_users[user]
                self._user_locks.pop(user, None)

    async def _checked_login(
        self,
        processor: UaProcessor,
        requesthdr: Any,
        token: ua.UserNameIdentityToken,
        address: str,
        user: str,
        call: Callable[[], Any],
    ) -> Any:
        verified = await self._verify_off_loop(processor, requesthdr, token)
        try:
            result = await self._audited(processor, address, user, call, token)
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

    def certificate_user(self, token: ua.X509IdentityToken) -> str:
        """Who an X509IdentityToken claims to be, for the audit trail and a session's identity: the user
        its certificate is bound to, else the certificate's thumbprint (checked or not)."""
        der = first_certificate(token.CertificateData or b"")
        found = self.app.users.user_of_certificate(der)
        return found[0] if found is not None else f"certificate {thumbprint(der)}"

    def answer_deadline(self, processor: UaProcessor, requesthdr: Any) -> float:
        """When (``time.monotonic()``) an ActivateSession must have its answer out, less the margin to
        check the password and send it (decision 65): before asyncua closes a connection without an
        activated session (``[limits] activation_timeout`` from connecting), before an activated
        session's own timeout, within the request's TimeoutHint when the client gives one, and before
        the channel's security token expires."""
        now = time.monotonic()
        session = processor.session
        deadlines = []
        if session is None or not session.is_activated():
            window = float(self.app.config.limits.activation_timeout)
            started = float(door.tagged(processor, "connected", now))
            deadlines.append(started + window - login_answer_margin(window))
        elif session.session_timeout:
            window = float(session.session_timeout)
            deadlines.append(now + window - login_answer_margin(window))
        hint = float(getattr(requesthdr, "TimeoutHint", 0) or 0) / 1000.0
        if hint > 0:
            deadlines.append(now + hint - login_answer_margin(hint))
        token = getattr(connection(processor), "security_token", None)
        lifetime = float(getattr(token, "RevisedLifetime", 0) or 0) / 1000.0
        created = getattr(token, "CreatedAt", None)
        if lifetime > 0 and isinstance(created, datetime):  # the channel's token, renewed by the client
            left = (created + timedelta(seconds=lifetime) - datetime.now(UTC)).total_seconds()
            deadlines.append(now + left - login_answer_margin(lifetime))
        return min(deadlines, default=now)

    async def _unchecked(self, processor: UaProcessor, address: str, user: str, token: Any, why: str) -> NoReturn:
        """Answer Bad_UserAccessDenied now, without checking the password (and without counting a
        failure): the throttle may not check it before its deadline (decision 65)."""
        log.info("login of user %r from %s refused unchecked: %s", user, address, why)
        await self._audit_login(processor, address, user, token, ua.StatusCodes.BadUserAccessDenied)
        raise ServiceError(ua.StatusCodes.BadUserAccessDenied)

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
            # The same checks and decryption as the activation itself (no side effects); it runs again.
            name, password = self.decrypt_user_token(isession, token)
        except Exception:
            return None  # the activation refuses the token itself
        async with self.password_checks:
            loop = asyncio.get_running_loop()
            role = await loop.run_in_executor(self._password_threads, self.app.users.verify, name, password or "")
        return verified_login.set((name, password or "", role))

    async def _audited(
        self, processor: UaProcessor, address: str, user: str | None, call: Callable[[], Any], token: Any
    ) -> Any:
        """Run an activation and record it in the audit trail and its audit event, refused or not."""
        try:
            result = await call()
        except ServiceError as exc:
            refused = self._refused_user_certificates.pop(processor.session, None) if processor.session else None
            if refused is not None:  # the certificate's own audit event besides the session's (decision 102)
                await self.audit_events.certificate_refused(*refused)
            await self._audit_login(processor, address, user, token, exc.code)
            raise
        except InvalidSignature:  # asyncua's check of the clientSignature (OPC 10000-4 5.7.3.2)
            code = _S.BadApplicationSignatureInvalid
            self.refusals.report(
                address,
                "application-signature",
                f"refused activation from {address}: its clientSignature does not verify with the certificate "
                f"of its channel over the server's certificate and nonce (BadApplicationSignatureInvalid)",
            )
            await self._audit_login(processor, address, user, token, code)
            raise ServiceError(code) from None
        await self._audit_login(processor, address, user, token, _S.Good)
        return result

    async def _audit_login(self, processor: UaProcessor, address: str, user: str | None, token: Any, code: int) -> None:
        from uacell.services.observers import session_fields

        fields = session_fields(processor.session) if processor.session is not None else {}
        fields["user"] = user or fields.get("user", "anonymous")
        self.app.audit.record("login", **fields, address=address, result=ua.StatusCode(code).name)
        await self.audit_events.session_activated(processor.session, channel_id(processor), token, user, code)

    def recheck_identities(self) -> int:
        """Decision 99: each session logged in as a user goes on as anonymous once ``users.toml`` no longer
        grants what its login was granted on (the user removed, their role changed, their password
        changed, or the certificate they logged in with unbound). Returns how many sessions it changed."""
        users, changed = self.app.users, 0
        for session in external_sessions(self.server.iserver):
            user = getattr(session, "user", None)
            if not isinstance(user, UacellUser) or user.anonymous or not user.name:
                continue
            if users.grants(
                user.name, user.uacell_role, password_hash=user.password_hash, certificate=user.certificate
            ):
                continue
            cast(UacellSession, session).go_on_as_anonymous(
                "identity_revoked", f"{users.path} no longer grants user {{user!r}} the login of this session"
            )
            changed += 1
        return changed

    def watch_users(self, interval: float = USERS_WATCH_INTERVAL) -> Callable[[], Awaitable[None]]:
        """Look at ``users.toml`` every ``interval`` seconds and ``recheck_identities`` when it was written
        (``uacell user`` changes it from another process); returns what stops the watch."""
        users = self.app.users

        async def watch() -> None:
            seen = users.stamp
            while True:
                await asyncio.sleep(interval)
                if users.stamp != seen:
                    seen = users.stamp
                    try:
                        self.recheck_identities()
                    except Exception:  # a file being written by hand: the next change is looked at again
                        log.exception("cannot check the sessions' users against %s", users.path)

        return _watching(watch(), "uacell-users-watch")


async def _nothing_to_stop() -> None:
    return None


def _watching(watch: Coroutine[Any, Any, None], name: str) -> Callable[[], Awaitable[None]]:
    """Run ``watch`` as a task of the loop; returns what stops it (``stop_task``)."""
    return functools.partial(stop_task, asyncio.get_running_loop().create_task(watch, name=name))


def _utc_now() -> datetime:
    return datetime.now(UTC)


class _TrustWatch:
    """Decision 100: the open secure channels follow the trust list's files whoever changes them, and
    the instants at which the same files judge otherwise (a revocation list past its nextUpdate, a CA's
    certificate at the end of its validity)."""

    trust_list: TrustList | None
    on_trust_changed: list[Callable[[], None]]

    def recheck_channels(self, anchors: Anchors | None = None, now: datetime | None = None) -> list[str]:
        raise NotImplementedError  # _Channels'

    def channel_expired(self, now: datetime) -> bool:
        raise NotImplementedError  # _Channels'

    def watch_trust(
        self, interval: float = TRUST_WATCH_INTERVAL, clock: Callable[[], datetime] = _utc_now
    ) -> Callable[[], Awaitable[None]]:
        """Look at ``pki/trusted/``, ``pki/issuers/`` and ``pki/crl/`` every ``interval`` seconds
        (``trust_stamp``); after a change, once the time ``next_change`` named for the files has come
        (``clock``), or once a certificate an open channel was accepted with has expired (decision 104),
        ``recheck_channels`` and tell ``on_trust_changed``. Returns what stops the watch."""
        trust = self.trust_list

        async def watch(paths: PkiPaths) -> None:
            seen, due = trust_stamp(paths), next_change(read_anchors(paths), clock())
            while True:
                await asyncio.sleep(interval)
                stamp, now = trust_stamp(paths), clock()
                # a list is stale once nextUpdate < now
                if stamp == seen and (due is None or now <= due) and not self.channel_expired(now):
                    continue
                try:
                    anchors = read_anchors(paths)
                    closed = self.recheck_channels(anchors, now)
                except Exception:  # a file half written by hand: looked at again at the next change
                    log.exception("cannot check the secure channels against %s", paths.root)
                    continue
                seen, due = stamp, next_change(anchors, now)
                if closed:
                    log.info("closed %d secure channel(s) the trust list no longer admits", len(closed))
                for changed in self.on_trust_changed:
                    try:
                        changed()
                    except Exception:
                        log.exception("telling of a trust list change failed")

        if trust is None:
            return _nothing_to_stop
        return _watching(watch(trust.paths), "uacell-trust-watch")


class _Channels:
    """The secure-channel part of ``Security``, the server's channel guard (ua/pipeline.py): a channel's
    opening checked and audited, its closing audited, and the client certificate (with the issuers sent
    with it) checked at CreateSession."""

    refusals: RefusalLog
    certificate_validator: CertificateValidator
    audit_events: SecurityAuditEvents
    trust_list: TrustList | None
    _channel_requests: weakref.WeakKeyDictionary[UaProcessor, ChannelRequest]
    _checked_chains: weakref.WeakKeyDictionary[UaProcessor, list[x509.Certificate]]
    _renewals: weakref.WeakKeyDictionary[UaProcessor, ChannelRequest]

    def check_channel(self, processor: UaProcessor, uri: str | None, mode: ua.MessageSecurityMode | None) -> None:
        raise NotImplementedError  # Security's

    def _report_certificate_refusal(self, message: str, reason: str) -> None:
        address = _address(context.current_processor())
        self.refusals.report(address, f"certificate:{reason}", f"{message} (client address {address})")

    def recheck_channels(self, anchors: Anchors | None = None, now: datetime | None = None) -> list[str]:
        """OPC 10000-12 7.8.2.5: once the trust list has changed, the secure channels whose client
        certificate it no longer admits are closed (a session of theirs goes on only over a channel that
        passes the check). A channel's certificate is checked, as at CreateSession, with the issuers its
        sessions sent (node-opcua sends its chain there, its certificate alone with the channel); a
        channel no session was created on was never checked, and is left to CreateSession's check. Under
        trust on first use, a certificate that is merely no longer trusted keeps its channel: it would be
        trusted again on its next one. ``anchors``: the files as just read (by default read now).
        Returns the closed channels' ids."""
        trust = self.trust_list
        if trust is None:
            return []
        anchors = anchors if anchors is not None else read_anchors(trust.paths)
        now, closed = now or datetime.now(UTC), []
        for processor, chain in list(self._checked_chains.items()):
            if not channel_open(processor):
                continue
            refusal = self._channel_refusal(trust, chain, anchors, now)
            if refusal is None:
                continue
            _log_refused(
                processor, chain, refusal, "closing secure channel %s from %s: the trust list no longer admits"
            )
            closed.append(channel_id(processor))
            close_channel(processor)
        return closed

    @staticmethod
    def _channel_refusal(
        trust: TrustList, chain: list[x509.Certificate], anchors: Anchors, now: datetime
    ) -> Refusal | None:
        """Why an open channel's chain is no longer admitted, or None: its own certificate out of its
        validity (decision 104), or the chain refused by the files; under trust on first use a
        certificate merely no longer trusted is admitted (it would be trusted again on its next channel)."""
        leaf = chain[0]
        if not leaf.not_valid_before_utc <= now <= leaf.not_valid_after_utc:
            return Refusal(_S.BadCertificateTimeInvalid, leaf, "it is not valid now")
        refusal = check_chain(chain, anchors, now, require_crls=trust.require_revocation_lists)
        if refusal is not None and trust.trust_on_first_use and refusal.code == _S.BadCertificateUntrusted:
            return None
        return refusal

    async def check_client_certificate(self, params: ua.CreateSessionParameters) -> ua.CreateSessionParameters:
        """The client's certificate, alone or followed by its issuers (OPC 10000-6 6.2.6), against the
        trust list; returns the parameters with the client's own certificate alone, as asyncua reads it."""
        processor = context.current_processor()
        address = _address(processor)
        try:
            chain = split_chain(params.ClientCertificate)
        except ValueError as exc:
            self.refusals.report(
                address, "session:certificate", f"refused session from {address}: its ClientCertificate {exc}"
            )
            raise ServiceError(_S.BadCertificateInvalid) from exc
        opened_with = channel.peer_certificate(processor) if processor is not None else None
        if opened_with is not None and der_of(chain[0]) != opened_with:
            # OPC 10000-4 5.7.2.2: the certificate the channel was opened with, whose key the channel proved
            self.refusals.report(
                address,
                "session:other-certificate",
                f"refused session from {address}: its ClientCertificate ({app_thumbprint(der_of(chain[0]))}) is not "
                f"the certificate its secure channel was opened with ({app_thumbprint(opened_with)})",
            )
            raise ServiceError(_S.BadSecurityChecksFailed)
        chain += self._issuers_sent_with_channel(chain[0])
        uri = (params.ClientDescription.ApplicationUri if params.ClientDescription else None) or ""
        await self._check_chain_now(chain, uri)
        if processor is not None:  # what the channel is checked with again (decision 100)
            self._channel_checked(processor, chain)
        return dataclasses.replace(params, ClientCertificate=der_of(chain[0]))

    async def _check_chain_now(self, chain: list[x509.Certificate], uri: str) -> None:
        """The client's chain against the trust list as it is now; a refusal fires its audit event besides
        the session's (OPC 10000-4 6.5.6) and raises ServiceError with the code the client is told."""
        verdict = self.certificate_validator.check(chain, uri)
        if verdict is not None:
            await self.audit_events.certificate_refused(verdict.precise, verdict.certificate, verdict.why, uri)
            raise ServiceError(verdict.told)

    def _channel_checked(self, processor: UaProcessor, chain: list[x509.Certificate]) -> None:
        known = self._checked_chains.setdefault(processor, [chain[0]])
        known += [c for c in chain[1:] if c not in known]

    def channel_expired(self, now: datetime) -> bool:
        """Has a certificate an open channel was accepted with (its own, or an issuer it sent) reached the
        end of its validity? (OPC 10000-4 6.1.7: checks between renewals are the server's to make.)"""
        return any(
            channel_open(p) and any(c.not_valid_after_utc < now for c in chain)
            for p, chain in list(self._checked_chains.items())
        )

    def checked_chain(self, processor: UaProcessor | None) -> list[x509.Certificate]:
        """The chain the channel's client certificate was last accepted with (empty: none yet)."""
        return list(self._checked_chains.get(processor, ())) if processor is not None else []

    def _issuers_sent_with_channel(self, cert: x509.Certificate) -> list[x509.Certificate]:
        """The issuers the client sent with the same certificate when it opened the secure channel (a
        client may send its chain there and its certificate alone at CreateSession, as node-opcua does)."""
        processor = context.current_processor()
        request = self._channel_requests.get(processor) if processor is not None else None
        sent = request.certificate if request is not None else None
        if not sent:
            return []
        try:
            chain = split_chain(sent)
        except ValueError:
            return []
        return chain[1:] if der_of(chain[0]) == der_of(cert) else []

    def refuse_channel(self, processor: UaProcessor, refused: _ChannelRefused) -> None:
        """Answer a refused OpenSecureChannel with an Error message (OPC 10000-6, 7.1.2.5); the caller
        then closes the connection."""
        channel.send_error(processor, refused.code, refused.reason)

    async def opening(
        self, processor: UaProcessor, header: ua.Header, body: Buffer, proceed: Callable[[], Awaitable[Any]]
    ) -> Any:
        """An OpenSecureChannel message: refused unless an offered endpoint allows its policy (asyncua
        would fall back to its initial None policy when no offered policy matches)."""
        return await self._checked_opening(processor, header, body, proceed, "")

    def open(self, processor: UaProcessor, algohdr: Any, body: Buffer) -> None:
        """The channel's requested security mode, checked before asyncua opens it."""
        self._channel_requests[processor] = request = _channel_request(algohdr, body)
        self.check_channel(processor, algohdr.SecurityPolicyURI, request.mode)

    async def renewing(
        self, processor: UaProcessor, header: ua.Header, body: Buffer, proceed: Callable[[], Awaitable[Any]]
    ) -> Any:
        """An OpenSecureChannel on an open channel, which renews its token: audited as every
        OpenSecureChannel is (OPC 10000-5 6.4.6, RequestType Renew), refused (an Error message, and the
        connection closed) when ``renew`` finds the certificate no longer admitted."""
        return await self._checked_opening(processor, header, body, proceed, channel_id(processor))

    async def _checked_opening(
        self,
        processor: UaProcessor,
        header: ua.Header,
        body: Buffer,
        proceed: Callable[[], Awaitable[Any]],
        renewed: str,
    ) -> Any:
        """An OpenSecureChannel (``renewed``: the id of the open channel whose token it renews) checked
        and audited, refused or not. A message asyncua's own checks refuse (a signature that does not
        verify, a secret that does not decrypt: a client holding a certificate but not its key) is
        audited too, with the certificate it sent (decision 106), then refused by the pipeline in one
        line, with an Error message."""
        sent = _peek_algorithm_header(header, body)
        uri = sent.SecurityPolicyURI if sent is not None else None
        certificate = (sent.SenderCertificate or None) if sent is not None else None
        try:
            if not renewed:
                self.check_channel(processor, uri, None)
            result = await proceed()
        except _ChannelRefused as refused:
            self.refuse_channel(processor, refused)
            await self._audit_channel(processor, uri, refused.code, refused.reason, renewed=renewed)
            return False  # the connection is closed
        except (ua.UaError, ServiceError, InvalidSignature, ValueError) as exc:
            code = getattr(exc, "code", None) or _S.BadSecurityChecksFailed
            why = "its signature does not verify" if isinstance(exc, InvalidSignature) else str(exc) or repr(exc)
            await self._audit_channel(processor, uri, code, why, renewed=renewed, sent=certificate)
            raise ServiceError(code) from exc
        if renewed or channel_open(processor):
            await self._audit_channel(processor, uri, _S.Good, renewed=renewed)
        return result

    def renew(self, processor: UaProcessor, algohdr: Any, body: Buffer) -> None:
        """OPC 10000-4 6.1.7: the client's certificate is verified again at every renewal of the channel's
        token, with the chain CreateSession accepted (a channel no session was created on is left to
        CreateSession, as at its opening) and the trust list's files as they are now."""
        self._renewals[processor] = _channel_request(algohdr, body)
        chain, trust = self._checked_chains.get(processor), self.trust_list
        if not chain or trust is None:
            return
        refusal = self._channel_refusal(trust, chain, read_anchors(trust.paths), datetime.now(UTC))
        if refusal is None:
            return
        _log_refused(
            processor, chain, refusal, "refused to renew secure channel %s from %s: the trust list no longer admits"
        )
        code = told(refusal.code, own=refusal.certificate == chain[0])
        raise _ChannelRefused(code, f"the client certificate is no longer admitted ({ua.StatusCode(code).name})")

    async def closing(self, processor: UaProcessor, proceed: Callable[[], Awaitable[Any]]) -> Any:
        """A client's CloseSecureChannel: audited (OPC 10000-4 6.5.5)."""
        closed = channel_id(processor)
        result = await proceed()
        if closed:
            await self.audit_events.channel_closed(closed)
        return result

    async def _audit_channel(
        self,
        processor: UaProcessor,
        uri: str | None,
        code: int,
        why: str = "",
        *,
        renewed: str = "",
        sent: bytes | None = None,
    ) -> None:
        """The audit event of an OpenSecureChannel (refused before asyncua read its request: what its
        header said, ``sent`` the certificate in it); ``renewed``: the id of the open channel whose token
        it renews."""
        if renewed:
            request = self._renewals.pop(processor, None)
            kind = ua.SecurityTokenRequestType.Renew
        else:
            request, kind = self._channel_requests.get(processor), ua.SecurityTokenRequestType.Issue
        if request is None:
            request = ChannelRequest(sent, uri or "", ua.MessageSecurityMode.Invalid, kind, 0.0)
        opened = renewed or (channel_id(processor) if ua.StatusCode(code).is_good() else "")
        await self.audit_events.channel_opened(request, opened, code, why)


class Security(_Channels, _TrustWatch, _Logins):
    """The security setup of one server (asyncua objects reach it as ``channel.attached(iserver, "security")``)."""

    def __init__(self, app: Host) -> None:
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
        # Threads of their own: a login never waits for other work in the loop's default executor
        # (history reads, program files), however much of it there is.
        self._password_threads = ThreadPoolExecutor(limits.password_checks, thread_name_prefix="uacell-password")
        self.on_session_closed: list[Callable[[InternalSession], None]] = []
        self.on_trust_changed: list[Callable[[], None]] = []  # told after the trust list's files changed
        self._user_locks: dict[str, asyncio.Lock] = {}
        self._lock_users: dict[str, int] = {}
        self.trust_list: TrustList | None = None
        self.policies: list[ua.SecurityPolicyType] = []
        self.refusals = RefusalLog()
        # what each channel's OpenSecureChannel asked for; its certificate: the client's, or its chain (10000-6 6.2.6)
        self._channel_requests: weakref.WeakKeyDictionary[UaProcessor, ChannelRequest] = weakref.WeakKeyDictionary()
        # a user certificate refused in a session's activation: (certificate step, DER, why) for its event
        self._refused_user_certificates: weakref.WeakKeyDictionary[InternalSession, tuple[int, bytes, str]] = (
            weakref.WeakKeyDictionary()
        )
        # the chain each channel's certificate was accepted with at CreateSession (recheck_channels)
        self._checked_chains: weakref.WeakKeyDictionary[UaProcessor, list[x509.Certificate]] = (
            weakref.WeakKeyDictionary()
        )
        # what a renewal of each channel's token asked for, until its audit event is fired
        self._renewals: weakref.WeakKeyDictionary[UaProcessor, ChannelRequest] = weakref.WeakKeyDictionary()
        self.role_node = ua.NodeId()  # Server/CurrentRole, made by install()
        self.user_node = ua.NodeId()  # Server/CurrentUser, made by install()

    async def install(self) -> None:
        cfg = self.app.config.server
        policy = self.app.policy
        iserver = self.server.iserver
        channel.attach(iserver, "security", self)
        await prepare_certificate(self.server, self.app.data_dir, self.server.get_application_uri(), [cfg.host])
        limit = RejectedLimit(cfg.rejected_max_files, cfg.rejected_max_age_days * 86400.0)
        self.trust_list = TrustList(
            PkiPaths.in_data_dir(self.app.data_dir),
            trust_on_first_use=cfg.trust_on_first_use,
            require_revocation_lists=cfg.require_revocation_lists,
            rejected_limit=limit,
            report_refusal=self._report_certificate_refusal,
        )
        if cfg.trust_on_first_use:
            log.warning(
                "trust_on_first_use is on: every new client certificate is trusted and kept in %s",
                self.trust_list.paths.trusted,
            )
        self.certificate_validator = CertificateValidator(self.trust_list)  # at CreateSession, with the chain
        self.audit_events = SecurityAuditEvents(self.server)
        await self.audit_events.install()
        self.policies = list(SECURE_POLICIES) + ([_P.NoSecurity] if policy.none_security else [])
        self.server.set_security_policy(self.policies)
        # asyncua gives the certificate token policy the endpoint's security policy (on a None endpoint the
        # first one that signs), so that a user certificate's signature always has an algorithm.
        self.server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken, ua.X509IdentityToken])
        door.swap(iserver, "InternalServer.create_session", self._create_session)
        door.swap(iserver, "InternalServer.decrypt_user_token", self.decrypt_user_token)
        door.swap(iserver, "InternalServer.verify_x509_token", self.verify_user_certificate)
        await self._add_session_variables()
        logging.getLogger("asyncua.server.uaprocessor").addFilter(_drop_fault_echo)  # added once
        context.add_read_hook(_read_hook)
        log.info(
            "security: endpoints %s; anonymous clients are %s",
            ", ".join(p.name for p in self.policies),
            policy.anonymous_role.label,
        )

    # sessions ------------------------------------------------------------------------------------

    def _create_session(self, name: Any, user: Any = None, external: bool = False) -> InternalSession:
        iserver = self.server.iserver
        if user is None:
            return UacellSession(self, iserver, iserver.aspace, iserver.subscription_service, name, external=external)
        return UacellSession(
            self, iserver, iserver.aspace, iserver.subscription_service, name, user=user, external=external
        )

    def session_closed(self, session: InternalSession) -> None:
        for hook in self.on_session_closed:
            try:
                hook(session)
            except Exception:
                log.exception("session-closed hook failed")

    # endpoints -----------------------------------------------------------------------------------

    def endpoints(self) -> list[ua.EndpointDescription]:
        """The endpoints this server offers (asyncua fills them in when the server starts)."""
        return list(self.server.iserver.endpoints)

    def channel_refusal(
        self, uri: str | None, mode: ua.MessageSecurityMode | None, *, discovery: bool = False
    ) -> int | None:
        """Bad_SecurityPolicyRejected or Bad_SecurityModeRejected unless an offered endpoint has this
        policy (and, when given, this mode); None when it does. With ``discovery``, policy None with mode
        None is always accepted (for GetEndpoints and FindServers only)."""
        same_policy = [e for e in self.endpoints() if e.SecurityPolicyUri == uri]
        if not same_policy and discovery and uri == SecurityPolicyNone.URI:
            return int(_S.BadSecurityModeRejected) if mode not in (None, ua.MessageSecurityMode.None_) else None
        if not same_policy:
            return int(_S.BadSecurityPolicyRejected)
        if mode is not None and all(e.SecurityMode != mode for e in same_policy):
            return int(_S.BadSecurityModeRejected)
        return None

    def check_channel(self, processor: UaProcessor, uri: str | None, mode: ua.MessageSecurityMode | None) -> None:
        """At OpenSecureChannel: raise _ChannelRefused for a policy or mode no offered endpoint has
        (policy None passes, for discovery: ``check_service`` limits what it may ask)."""
        code = self.channel_refusal(uri, mode, discovery=True)
        if code is None:
            return
        what = f"security policy {uri}" if code == _S.BadSecurityPolicyRejected else f"security mode {mode}"
        self.refusals.report(
            _address(processor),
            f"channel:{code}",
            f"refused secure channel from {_address(processor)}: {what} is not offered ({ua.StatusCode(code).name})",
        )
        raise _ChannelRefused(code, f"{what} is not offered by this server")

    def endpoint_of(self, processor: UaProcessor | None) -> ua.EndpointDescription | None:
        """The offered endpoint whose policy and mode the processor's channel uses."""
        uri, mode = _channel_policy(processor)
        for endpoint in self.endpoints():
            if endpoint.SecurityPolicyUri == uri and endpoint.SecurityMode == mode:
                return endpoint
        return None

    def check_service(self, processor: UaProcessor, typeid: ua.NodeId) -> None:
        """On a channel that is no offered endpoint (policy None kept for discovery), refuse every request
        but discovery with Bad_SecurityPolicyRejected."""
        if typeid in _DISCOVERY or self.endpoint_of(processor) is not None:
            return
        address = _address(processor)
        uri, mode = _channel_policy(processor)
        self.refusals.report(
            address,
            "service",
            f"refused request from {address} on a {uri.rsplit('#', 1)[-1]}/{mode.name} channel: "
            "no such endpoint is offered, only discovery is served (Bad_SecurityPolicyRejected)",
        )
        raise ServiceError(_S.BadSecurityPolicyRejected)

    def check_session(self, processor: UaProcessor | None, params: ua.CreateSessionParameters) -> None:
        """At CreateSession (OPC 10000-4, 5.6.2): the channel's policy and mode must be an offered
        endpoint's, and the EndpointUrl an opc.tcp URL."""
        address = _address(processor)
        uri, mode = _channel_policy(processor)
        code = self.channel_refusal(uri, mode)
        if code is not None:
            self.refusals.report(
                address,
                f"session:{code}",
                f"refused session from {address}: its channel ({uri}, {mode.name}) is not an "
                f"offered endpoint ({ua.StatusCode(code).name})",
            )
            raise ServiceError(code)
        url = params.EndpointUrl
        if url and urlparse(url).scheme.lower() != "opc.tcp":
            self.refusals.report(
                address, "session:url", f"refused session from {address}: EndpointUrl {url!r} is not an opc.tcp URL"
            )
            raise ServiceError(_S.BadTcpEndpointUrlInvalid)

    async def check_reassociation(self, processor: UaProcessor, auth_token: ua.NodeId, body: Buffer) -> None:
        """ActivateSession of an existing session on a new secure channel (OPC 10000-4, 5.6.3.1): only for an
        activated session, from a channel with the same client certificate, with the same identity, and
        (decision 104) a certificate chain the trust list admits now, checked as CreateSession checks it;
        the new channel is then checked again with that chain whenever the trust list changes."""
        session = self.server.iserver.lookup_external_session(auth_token)
        if not isinstance(session, UacellSession):
            return  # asyncua answers Bad_SessionIdInvalid
        address = _address(processor)
        if not session.is_activated():
            code, why = _S.BadSessionNotActivated, "it was never activated on the channel that created it"
        elif session.channel_certificate != channel.peer_certificate(processor):
            code, why = _S.BadSecurityChecksFailed, "the new channel's client certificate is not the session's"
        else:
            params = struct_from_binary(ua.ActivateSessionParameters, body.copy())
            token = params.UserIdentityToken
            name = token.UserName if isinstance(token, ua.UserNameIdentityToken) else None
            if isinstance(token, ua.X509IdentityToken):
                name = self.certificate_user(token)
            if name != getattr(session.user, "name", None):
                code, why = _S.BadIdentityChangeNotSupported, "the identity differs from the session's"
            else:
                chain = list(session.client_chain)
                if chain:  # created on a channel with a certificate: the trust list decides again
                    uri = session.client_description.ApplicationUri if session.client_description else None
                    await self._check_chain_now(chain, uri or "")
                    self._channel_checked(processor, chain)
                return
        self.refusals.report(
            address,
            f"reassociation:{code}",
            f"refused to move a session to a new channel from {address}: {why} ({ua.StatusCode(code).name})",
        )
        raise ServiceError(code)

    def message_refused(self, processor: UaProcessor, exc: Exception) -> None:
        """A message asyncua refused below the request stages (a chunk of a channel it does not know,
        a bad signature, an unexpected message type): one INFO line per address and interval, an
        Error message to the client; the pipeline then closes the connection."""
        code = getattr(exc, "code", None) or ua.StatusCodes.BadSecurityChecksFailed
        address = _address(processor)
        name = ua.StatusCode(code).name
        self.refusals.report(address, f"message {name}", f"refused a message from {address}: {exc} ({name})")
        with contextlib.suppress(Exception):
            channel.send_error(processor, code, str(exc)[:200])

    # logins --------------------------------------------------------------------------------------

    def refuse_plaintext(self, token: ua.UserNameIdentityToken) -> None:
        """A password travels in clear text unless the token or the channel is encrypted: refuse that."""
        processor = context.current_processor()
        if token.EncryptionAlgorithm or _channel_mode(processor) == ua.MessageSecurityMode.SignAndEncrypt:
            return
        log.info(
            "refused login of user %r from %s: clear-text password on an unencrypted channel",
            token.UserName,
            _address(processor),
        )
        raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)

    def _invalid_token(self, token: ua.UserNameIdentityToken, reason: str, why: str) -> ServiceError:
        address = _address(context.current_processor())
        self.refusals.report(
            address,
            f"token:{reason}",
            f"refused login of user {token.UserName!r} from {address}: {why} (Bad_IdentityTokenInvalid)",
        )
        return ServiceError(_S.BadIdentityTokenInvalid)

    def token_security_policy(self, kind: ua.UserTokenType, policy_id: str | None) -> str | None:
        """The security policy URI of the user token policy ``policy_id`` of this kind that the current
        request's endpoint offers (the endpoint's own when the token policy names none); None when the
        endpoint offers no such policy."""
        endpoint = self.endpoint_of(context.current_processor())
        if endpoint is None:
            return None
        for policy in endpoint.UserIdentityTokens:
            if policy.TokenType == kind and policy.PolicyId == policy_id:
                return str(policy.SecurityPolicyUri or endpoint.SecurityPolicyUri or "")
        return None

    def decrypt_user_token(self, isession: InternalSession, token: ua.UserNameIdentityToken) -> tuple[str, str]:
        """asyncua's hook for user-name tokens: (user name, password), or ServiceError.

        The token must name a user token policy of the session's endpoint; an encrypted password must
        use that policy's algorithm and end with the server nonce last sent to this session."""
        self.refuse_plaintext(token)
        policy_uri = self.token_security_policy(ua.UserTokenType.UserName, token.PolicyId)
        if policy_uri is None:
            raise self._invalid_token(token, "policy", f"no user-name token policy {token.PolicyId!r} on this endpoint")
        expected = _TOKEN_ALGORITHM.get(policy_uri or "", "")
        algorithm = token.EncryptionAlgorithm or ""
        if algorithm != expected:
            wanted = expected or "no encryption"
            raise self._invalid_token(
                token, "algorithm", f"password encrypted with {algorithm or 'nothing'}, the endpoint asks for {wanted}"
            )
        password = token.Password or b""
        if not algorithm:
            return token.UserName, password.decode("utf-8") if isinstance(password, bytes) else str(password)
        try:
            plain = _DECRYPT[algorithm](self.server.iserver.private_key, password)
            secret = open_token_secret(plain, isession.nonce)
            return token.UserName, secret.decode("utf-8")
        except ValueError as exc:  # includes cryptography's decryption errors and UnicodeDecodeError
            raise self._invalid_token(token, "secret", str(exc) or "the password cannot be decrypted") from None

    def verify_user_certificate(
        self, isession: InternalSession, token: ua.X509IdentityToken, signature: ua.SignatureData | None
    ) -> bytes:
        """asyncua's hook for X509IdentityTokens: the certificate (DER) when the token names a certificate
        token policy of the session's endpoint and passes ``check_user_certificate``, else ServiceError.
        ``UacellUserManager.get_user`` then finds its user."""
        address = _address(context.current_processor())
        policy_uri = self.token_security_policy(ua.UserTokenType.Certificate, token.PolicyId)
        try:
            if policy_uri is None:
                raise TokenRefused(_S.BadIdentityTokenInvalid, f"no certificate token policy {token.PolicyId!r} here")
            server_certificate = uacrypto.der_from_x509(self.server.iserver.certificate)
            nonce = isession.nonce or b""
            sent = sent_certificate(context.current_processor())
            login = check_user_certificate(
                token.CertificateData,
                signature.Algorithm if signature is not None else None,
                signature.Signature if signature is not None else None,
                policy_uri=policy_uri,
                challenge=server_certificate + nonce,
                now=datetime.now(UTC),
                chain_challenge=sent + nonce if sent and sent != server_certificate else None,
                users=self.app.users,
            )
        except TokenRefused as refused:
            name = ua.StatusCode(refused.code).name
            self.refusals.report(
                address,
                f"certificate:{refused.code}",
                f"refused certificate login from {address}: {refused.why} ({name})",
            )
            if refused.certificate_code is not None:  # its audit event, fired by ``_audited`` (decision 102)
                der = first_certificate(token.CertificateData or b"")
                self._refused_user_certificates[isession] = (refused.certificate_code, der, refused.why)
            raise ServiceError(refused.code) from None
        return VerifiedCertificate.of(first_certificate(token.CertificateData), login)

    # per-session attributes ------------------------------------------------------------------------

    async def _add_session_variables(self) -> None:
        """``Server/CurrentRole`` (decision 39) and ``Server/CurrentUser`` (decision 103): read by a
        session, the role and the user that session has."""
        self.role_node = await self._session_variable("CurrentRole", CURRENT_ROLE_DESCRIPTION)
        self.user_node = await self._session_variable("CurrentUser", CURRENT_USER_DESCRIPTION)

    async def _session_variable(self, name: str, description: str) -> ua.NodeId:
        ns = self.app.cell.instantiator.ns
        node_id = ua.NodeId(f"Server.{name}", ns)
        if node_id in self.server.iserver.aspace:  # restored from the address-space snapshot
            return node_id
        node = await self.server.get_node(ua.ObjectIds.Server).add_variable(
            node_id, ua.QualifiedName(name, ns), "", varianttype=ua.VariantType.String
        )
        await node.write_attribute(
            ua.AttributeIds.Description,
            ua.DataValue(ua.Variant(ua.LocalizedText(description, "en"), ua.VariantType.LocalizedText)),
        )
        return node_id

    def adjust_read(self, session: InternalSession, params: ua.ReadParameters, results: list[ua.DataValue]) -> None:
        role = caller_of(session).role
        aspace = self.server.iserver.aspace
        for i, (rv, dv) in enumerate(zip(params.NodesToRead, results, strict=False)):
            if dv.StatusCode is not None and not dv.StatusCode.is_good():
                continue
            attr = rv.AttributeId
            if attr == _A.Value and rv.NodeId == self.role_node:
                results[i] = _with_value(dv, Role.parse(role).label, ua.VariantType.String)
                continue
            if attr == _A.Value and rv.NodeId == self.user_node:
                results[i] = _with_value(dv, caller_of(session).user or "", ua.VariantType.String)
                continue
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
                    allowed = dv.Value.Value and self.app.dispatcher.roles.may_call(
                        Role.parse(role), "Write", Family.FILE
                    )
                    results[i] = _with_value(dv, allowed, ua.VariantType.Boolean)


def _with_value(dv: ua.DataValue, value: Any, vtype: ua.VariantType) -> ua.DataValue:
    return dataclasses.replace(dv, Value=ua.Variant(value, vtype))


def _read_hook(session: InternalSession, params: Any, results: list[Any]) -> None:
    security: Security | None = channel.attached(session.iserver, "security")
    if security is not None:
        security.adjust_read(session, params, results)


class UacellSession(LimitedSession):
    """A session that checks writes against the role table and reports its end."""

    nonce: bytes

    def __init__(self, security: Security, *args: Any, **kwargs: Any) -> None:
        self._security = security
        self.client_description: ua.ApplicationDescription | None = None
        self.channel_certificate: bytes | None = None  # the client certificate of the creating channel
        self.client_chain: tuple[x509.Certificate, ...] = ()  # that certificate and its issuers, as accepted
        self.client_address = ""
        self._audited_open = False
        self._expiry: asyncio.TimerHandle | None = None  # when a user certificate's credentials end
        super().__init__(*args, **kwargs)
        if self.external:
            # asyncua counts AuthenticationTokens up from 1000; OPC 10000-4 (7.31) asks for a secret.
            self.iserver.unregister_external_session(self)
            self.auth_token = ua.NodeId(ua.ByteString(os.urandom(32)), ua.Int16(0), ua.NodeIdType.ByteString)
            self.iserver.register_external_session(self)

    async def create_session(self, params: ua.CreateSessionParameters, sockname: Any = None) -> ua.CreateSessionResult:
        self.client_description = params.ClientDescription  # Caller.client: LockingClient shows it
        self.session_name = params.SessionName or ""  # the client's name for it (audit trail)
        processor = context.current_processor()
        self.client_address = _address(processor)
        if processor is not None:
            self.channel_certificate = channel.peer_certificate(processor)
        if _channel_mode(processor) == ua.MessageSecurityMode.None_:
            # OPC 10000-4 CreateSession: on a SecurityPolicy None channel the client certificate plays
            # no part (nothing is signed with it), so it is not checked against the trust list.
            params = dataclasses.replace(params, ClientCertificate=None)
        events = self._security.audit_events
        try:
            self._security.check_session(processor, params)
            if params.ClientCertificate:
                params = await self._security.check_client_certificate(params)
            result = await super().create_session(params, sockname=sockname)
            self.client_chain = tuple(self._security.checked_chain(processor))
        except BaseException as exc:
            await self.close_session()  # a refused session must not be activated later
            if isinstance(exc, ServiceError):
                await events.session_created(self, params, channel_id(processor), exc.code)
            raise
        self._audited_open = True
        self._audit("session_open")
        await events.session_created(self, params, channel_id(processor), _S.Good)
        diagnostics = self._security.app.diagnostics
        if diagnostics is not None:
            diagnostics.session_created(self, params, processor)
        return result

    def _end_cause(self) -> str:
        """Why the session is closing, as an AuditSessionEvent's SourceName says it (OPC 10000-4 6.5.6)."""
        timeout = float(self.session_timeout or 0)
        now = time.monotonic()
        if timeout > 0 and now - last_activity(self, now) >= timeout:
            return "Timeout"
        return "CloseSession" if context.current_processor() is not None else "Terminated"

    def _audit(self, event: str, **extra: Any) -> None:
        from uacell.services.observers import session_fields

        fields = {**session_fields(self), **extra}
        self._security.app.audit.record(event, **fields, address=self.client_address)

    def activate_session(
        self, params: ua.ActivateSessionParameters, peer_certificate: bytes | None
    ) -> ua.ActivateSessionResult:
        issued = self.nonce
        result = super().activate_session(params, peer_certificate)
        if self.nonce == issued:  # a nonce is never accepted twice: the next activation needs a fresh one
            self.nonce = create_nonce(32)
            result.ServerNonce = self.nonce
        self._watch_expiry()
        return result

    def _watch_expiry(self) -> None:
        """The identity just activated: a user certificate's credentials end when it expires, plus
        ``[users] certificate_grace`` (OPC 10000-4 7.41.5, decision 88); a new activation replaces the watch."""
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        expires = getattr(self.user, "expires", None)
        if expires is None:
            return
        grace = float(self._security.app.config.users.certificate_grace)
        left = (expires - datetime.now(UTC)).total_seconds() + grace
        self._expiry = asyncio.get_running_loop().call_later(max(0.0, left), self._identity_expired)

    def _identity_expired(self) -> None:
        """The session goes on with the anonymous role ("The Session shall stay valid with the Anonymous
        Role"); the client renews its credentials with ActivateSession."""
        self._expiry = None
        self.go_on_as_anonymous("identity_expired", "the certificate of user {user!r} expired")

    def go_on_as_anonymous(self, event: str, why: str) -> None:
        """The session's credentials end (``why``, with ``{user}`` for the user's name): it goes on with
        the anonymous role, logged and audited as ``event``."""
        if self.state == SessionState.Closed:
            return
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        name = getattr(cast(Any, self).user, "name", None)
        cast(Any, self).user = UacellUser(None, self._security.app.policy.anonymous_role.label, anonymous=True)
        log.info("%s: session %s goes on as anonymous", why.format(user=name), self.session_id)
        self._audit(event, user=name)

    async def write(self, params: ua.WriteParameters) -> list[ua.StatusCode]:
        check_operations(self.iserver, len(params.NodesToWrite or ()), "Write")
        return await self._security.app.writes.write(caller_of(self), params, super().write)

    async def close_session(self, delete_subs: bool = True) -> None:
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        already = self.state == SessionState.Closed
        await super().close_session(delete_subs)
        if not already:
            if self._audited_open:
                self._audit("session_close")
                await self._security.audit_events.session_closed(self, self._end_cause())
            if self._security.app.diagnostics is not None:
                self._security.app.diagnostics.session_closed(self)
            self._security.session_closed(self)


def _log_refused(processor: UaProcessor, chain: list[x509.Certificate], refusal: Refusal, doing: str) -> None:
    """One WARNING line: what is done to which channel (``doing`` names its id and address with two %s),
    the client's certificate, and why the files refuse it."""
    log.warning(
        doing + " its certificate %s (%s: %s)",
        channel_id(processor),
        _address(processor),
        app_thumbprint(der_of(chain[0])),
        refusal.name,
        refusal.why,
    )


def _channel_request(algohdr: Any, body: Buffer) -> ChannelRequest:
    """What an OpenSecureChannel asks for, read without consuming its body."""
    params = struct_from_binary(ua.OpenSecureChannelRequest, body.copy()).Parameters
    return ChannelRequest(
        algohdr.SenderCertificate or None,
        algohdr.SecurityPolicyURI or "",
        params.SecurityMode,
        params.RequestType,
        float(params.RequestedLifetime or 0),
    )


def _peek_algorithm_header(header: ua.Header, body: Buffer) -> ua.AsymmetricAlgorithmHeader | None:
    """An OpenSecureChannel's asymmetric security header (its policy and certificate: sent in clear),
    read without consuming the body; None when malformed (asyncua's own parsing refuses it)."""
    try:
        found: ua.AsymmetricAlgorithmHeader = struct_from_binary(
            ua.AsymmetricAlgorithmHeader, body.copy(header.body_size)
        )
    except Exception:
        return None
    return found


CURRENT_ROLE_DESCRIPTION = (
    "uacell: the role of the session that reads this value (observer, operator, engineer or admin); "
    "each session reads its own"
)
CURRENT_USER_DESCRIPTION = (
    "uacell: the user the session that reads this value is logged in as (empty: anonymous); each session reads its own"
)


class SecurityStage:
    """The request stage of security (``ua/pipeline.py``): the service allowed on this channel and for
    this session; ActivateSession re-associated, throttled, checked off the loop and audited."""

    def __init__(self, security: Security) -> None:
        self.security = security

    async def __call__(self, request: Request, call_next: Next) -> Any:
        security, processor = self.security, request.processor
        security.check_service(processor, request.typeid)
        if request.typeid != _ACTIVATE:
            return await call_next(request)
        if processor.session is None:  # a session created on another channel
            await security.check_reassociation(processor, request.header.AuthenticationToken, request.body)
        return await security.activate(processor, request.header, request.body, lambda: call_next(request))


def _identity_token(body: Any) -> Any:
    """The UserIdentityToken of an ActivateSession body, read without consuming it (None if unreadable)."""
    try:
        return struct_from_binary(ua.ActivateSessionParameters, body.copy()).UserIdentityToken
    except Exception:
        return None


async def install_security(app: Host) -> Security:
    """Set up certificates, endpoints, trust list, login rules and per-session rights for ``app``."""
    security = Security(app)
    await security.install()
    return security
