"""The HMI's places on the OPC UA server: which web session holds one of its ``[web] ua_sessions``
OPC UA sessions, and who waits for one (decision 64).

A place is taken before a connect starts and given back only once the session is closed
(``SessionSlots``), so the cap holds whatever the concurrency. A connected session without an open
page makes room for another; a page beyond the cap says "HMI busy" and gets the next place that
comes free, the page that waited longest first.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any

from uacell.core.companion import WebView
from uacell.web.uasession import CellCache, Credentials, SessionSlots, UaSession

log = logging.getLogger(__name__)

LOGIN_SLOT_WAIT = 10.0  # seconds a login waits for one of the HMI's OPC UA sessions to come free


@dataclass
class WebSession:
    id: str
    csrf: str
    ua: UaSession | None = None
    user: str | None = None
    last_seen: float = field(default_factory=time.monotonic)
    streams: int = 0  # pages open (or opening) on this session
    busy_since: float = 0.0  # when its page was last told "HMI busy" (the longest waiting is served first)
    admitting: asyncio.Event | None = None  # set when the request finding its OPC UA session a place is done
    ended_because: str = ""  # said to the page when the HMI ended the session itself


class Places:
    """The OPC UA sessions of the web sessions in ``sessions`` (the HMI's own table), at most
    ``ua_sessions`` of them. ``later`` runs a coroutine in a task of its own; ``refused`` ends a web
    session whose password the server no longer takes."""

    def __init__(
        self,
        url: str,
        credentials: Credentials,
        sessions: dict[str, WebSession],
        *,
        ua_sessions: int,
        anonymous: bool,
        later: Callable[[Coroutine[Any, Any, None]], None],
        refused: Callable[[WebSession, str], None],
        closing: asyncio.Event,
        views: Sequence[WebView] = (),
    ) -> None:
        self.url, self.credentials, self.sessions = url, credentials, sessions
        self.ua_sessions, self.anonymous = ua_sessions, anonymous
        self._later, self._refused, self._closing = later, refused, closing
        self.cells = CellCache(views)  # the parts of ``views`` (the companions' web views)
        self.slots = SessionSlots(ua_sessions)
        self.slots.on_free = self._freed
        self._admitting = False

    def busy_text(self) -> str:
        return f"this HMI already serves {self.ua_sessions} users with open pages; try again in a minute"

    def watch(self, s: WebSession, ua: UaSession) -> UaSession:
        """``ua`` counted in the places, and ``s`` ended when the server refuses its password."""
        ua.on_identity_refused = lambda exc: self._refused(s, ua.problem)
        ua.slots = self.slots
        return ua

    def new_login(self, s: WebSession, user: str, password: str) -> UaSession:
        return self.watch(s, UaSession(self.url, self.credentials, user=user, password=password, cache=self.cells))

    async def ua(self, s: WebSession) -> UaSession:
        """The session's OPC UA session: made anonymously on first use, made again after it was
        released, and "busy" (with the reason) while the HMI holds ``ua_sessions`` for open pages."""
        if s.ua is None:
            ua = self.watch(s, UaSession(self.url, self.credentials, cache=self.cells))
            s.ua = ua
            if s.user is None and not self.anonymous:
                ua.status = "login-required"
                ua.problem = "Log in to use this HMI: it takes no anonymous users on this address"
                return ua
            ua.status = "released"
        ua = s.ua
        if s.admitting is not None:  # another request of this session is finding it a place: its outcome
            await s.admitting.wait()
            return ua
        if ua.status in ("released", "busy"):
            s.admitting = asyncio.Event()  # one request at a time finds it a place
            try:
                if not await self.make_room(s, ua):
                    if ua.status != "busy":
                        s.busy_since = time.monotonic()
                    ua.wait_for_place(self.busy_text())
                    return ua
                await ua.resume()
            finally:
                s.admitting.set()
                s.admitting = None
            s.last_seen = time.monotonic()  # connecting took time: the page is about to use it
        return ua

    async def make_room(self, s: WebSession, ua: UaSession) -> bool:
        """Take a place for ``ua`` (of web session ``s``): a free one, or the one of the longest-unused
        web session without an open page, whose OPC UA session is released for it. Pages that are
        open (or opening) keep theirs, and so do sessions still connecting."""
        if self.slots.take(ua):
            return True
        idle = sorted(
            (
                x
                for x in self.sessions.values()
                if x is not s and x.streams == 0 and x.ua is not None and x.ua.status == "connected"
            ),
            key=lambda x: x.last_seen,
        )
        if not idle:
            return False
        victim = idle[0].ua
        assert victim is not None
        log.info("web: %d OPC UA sessions held; releasing the longest unused one", len(self.slots.holders))
        await victim.release()  # its place is free when this returns: taken in the same step
        return self.slots.take(ua)

    async def login_room(self, s: WebSession, ua: UaSession) -> bool:
        """A place for a login: a free one, an idle session's, the page's own anonymous one, or one
        that comes free within ``LOGIN_SLOT_WAIT`` (other logins end within seconds)."""
        if await self.make_room(s, ua):
            return True
        if s.ua is not None and s.ua.status == "connected":
            await s.ua.release()
            if self.slots.take(ua):
                return True
        if await self.slots.wait_take(ua, LOGIN_SLOT_WAIT):
            return True
        self.resume_later(s)
        return False

    def resume_later(self, s: WebSession) -> None:
        """After a login that did not happen: the page's own session comes back if a page is open."""
        if s.streams and s.ua is not None and s.ua.status in ("released", "busy"):
            self._later(self._resume(s))

    async def _resume(self, s: WebSession) -> None:
        await self.ua(s)

    def _freed(self) -> None:
        """A place came free: the page that has waited longest gets it (soon, in a task of its own)."""
        if not self._admitting and not self._closing.is_set():
            self._admitting = True
            self._later(self._admit_waiting())

    async def _admit_waiting(self) -> None:
        try:
            while self.slots.free > 0:
                waiting = [
                    x for x in self.sessions.values() if x.streams and x.ua is not None and x.ua.status == "busy"
                ]
                if not waiting:
                    return
                s = min(waiting, key=lambda x: x.busy_since)
                await self.ua(s)
                if s.ua is not None and s.ua.status == "busy":
                    return  # the server itself has no session free: the reaper tries again later
        finally:
            self._admitting = False
