"""The web HMI's HTTP side: pages, login, CSRF, server-sent events, calls (Starlette).

Each browser gets a web session (a random id in an HttpOnly, SameSite=Strict cookie, Secure over
HTTPS) that owns one ``UaSession``: anonymous until the user logs in with a name and password the
OPC UA server checks. Every state-changing request is a POST carrying the session's CSRF token in
the ``X-CSRF-Token`` header. Passwords travel only in POST bodies and are never logged.
"""

from __future__ import annotations

import asyncio
import html
import json
import logging
import math
import secrets
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Iterable, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

from uacell.core.companion import WebView
from uacell.web.guards import HostGuard
from uacell.web.history import MAX_HOURS as MAX_HISTORY_HOURS
from uacell.web.history import WIDTH as HISTORY_WIDTH
from uacell.web.places import Places, WebSession
from uacell.web.uasession import CallFailed, Credentials, UnknownKey, login_refusal

log = logging.getLogger(__name__)

COOKIE = "uacell_session"  # until the HMI knows its port (cookie_name)
IDLE_TIMEOUT = 30 * 60.0  # a web session nobody has used for this long ends (its OPC UA session too)
UA_SESSIONS = 50  # OPC UA sessions the HMI holds at once ([web] ua_sessions)
RELEASE_AFTER = 30.0  # seconds after its last page closed, a web session's OPC UA session is released
HEARTBEAT = 15.0
MAX_SESSIONS = 200  # beyond this, the longest unused web session (without a page open) ends
MAX_UPLOAD = 1_000_000


def cookie_name(port: int, https: bool) -> str:
    """The session cookie's name for the HMI on ``port``: browsers send a host's cookies to every port
    of it, so each HMI has its own name (two HMIs on one host never clobber each other's session),
    and over HTTPS the ``__Host-`` prefix keeps it to this exact host, Secure and path ``/``."""
    return f"__Host-uacell_{port}" if https else f"uacell_{port}"


def _static_dir() -> str:
    return str(resources.files("uacell.web") / "static")


class WebApp:
    """The HMI for one OPC UA server ``url``; ``app`` is the ASGI application."""

    def __init__(
        self,
        url: str,
        credentials: Credentials,
        *,
        https: bool = False,
        idle_timeout: float = IDLE_TIMEOUT,
        anonymous: bool = True,
        hosts: Iterable[str] = (),
        ua_sessions: int = UA_SESSIONS,
        release_after: float = RELEASE_AFTER,
        views: Sequence[WebView] = (),
    ) -> None:
        self.url = url
        # What the page shows: each companion's web view (``Companion.web_view``), its browser module
        # and stylesheet served from the companion's package at /views/<layout key>.js and .css.
        self.views = tuple(views)
        self._view_files = {
            f"{v.layout_key}.{kind}": file
            for v in self.views
            for kind, file in (("js", v.script), ("css", v.style))
            if file is not None
        }
        self.credentials = credentials
        # False: visitors must log in (the HMI is on the network, the OPC UA server on loopback, where
        # the server would grant anonymous clients the rights it means for the local machine only).
        self.anonymous = anonymous
        self.https = https
        self.cookie = COOKIE
        self.idle_timeout = idle_timeout
        self.ua_sessions = ua_sessions
        self.release_after = release_after
        self.sessions: dict[str, WebSession] = {}
        self.closing = asyncio.Event()
        self._reaper: asyncio.Task[None] | None = None
        self._ending: set[asyncio.Task[None]] = set()
        # What the HMI holds on the server: at most ``ua_sessions``, counted before a connect starts.
        self.places = Places(
            url,
            credentials,
            self.sessions,
            ua_sessions=ua_sessions,
            anonymous=anonymous,
            later=self._later,
            refused=self._refused,
            closing=self.closing,
            views=self.views,
        )
        static = _static_dir()
        routes = Starlette(
            routes=[
                Route("/", self.index),
                Route("/api/session", self.session_info),
                Route("/api/login", self.login, methods=["POST"]),
                Route("/api/logout", self.logout, methods=["POST"]),
                Route("/api/events", self.events),
                Route("/api/call", self.call, methods=["POST"]),
                Route("/api/file", self.file, methods=["POST"]),
                Route("/api/upload", self.upload, methods=["POST"]),
                Route("/api/delete", self.delete, methods=["POST"]),
                Route("/api/history", self.history),
                Route("/views/{name}", self.view_file),
                Mount("/static", StaticFiles(directory=static), name="static"),
            ]
        )
        # Only the names the HMI is served under (loopback names, IP addresses, ``hosts``): DNS rebinding.
        self.app = HostGuard(routes, names=hosts, https=https)
        self._index = self._page(Path(static, "index.html").read_text(encoding="utf-8"))

    # sessions --------------------------------------------------------------------------------

    def _new_session(self) -> WebSession:
        idle = sorted((x for x in self.sessions.values() if x.streams == 0), key=lambda x: x.last_seen)
        while len(self.sessions) >= MAX_SESSIONS and idle:
            oldest = idle.pop(0)
            self.sessions.pop(oldest.id, None)
            self._later(self._end(oldest))
        s = WebSession(secrets.token_urlsafe(32), secrets.token_urlsafe(32))
        self.sessions[s.id] = s
        if self._reaper is None or self._reaper.done():
            self._reaper = asyncio.get_running_loop().create_task(self._reap())
        return s

    def _session(self, request: Request) -> WebSession | None:
        """The web session of a request that carries both its cookie and its token (the ``X-CSRF-Token``
        header, or ``?key=`` for the event stream, which cannot send headers). Browsers send a
        host's cookies to every port of it, so a cookie alone may have been replayed by another
        program on this host; the token is kept in the page's own storage, which is per origin
        (scheme, host and port) and never reaches another port (decision 66)."""
        s = self._by_cookie(request)
        if s is None:
            return None
        token = request.headers.get("x-csrf-token") or request.query_params.get("key", "")
        if not secrets.compare_digest(token.encode(), s.csrf.encode()):
            log.info("web: a request to %s had a session cookie without its token: refused", request.url.path)
            return None
        return s

    def _by_cookie(self, request: Request) -> WebSession | None:
        s = self.sessions.get(request.cookies.get(self.cookie, ""))
        if s is not None:
            s.last_seen = time.monotonic()
        return s

    def _set_cookie(self, response: Response, s: WebSession) -> Response:
        response.set_cookie(self.cookie, s.id, httponly=True, samesite="strict", secure=self.https, path="/")
        return response

    async def _end(self, s: WebSession) -> None:
        self.sessions.pop(s.id, None)
        if s.ua is not None:
            await s.ua.close()
            s.ua = None

    def _later(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._ending.add(task)
        task.add_done_callback(self._ending.discard)

    async def _reap(self) -> None:
        while self.sessions and not self.closing.is_set():
            await asyncio.sleep(min(60.0, self.idle_timeout / 2, self.release_after / 2))
            now = time.monotonic()
            for s in list(self.sessions.values()):
                if s.streams:
                    if s.ua is not None and s.ua.status == "busy":  # an open page waits: a place may be free
                        await self.places.ua(s)
                    continue
                if now - s.last_seen > self.idle_timeout:
                    log.info("web session of %s ended after %.0f s unused", s.user or "anonymous", now - s.last_seen)
                    await self._end(s)
                elif (
                    s.ua is not None
                    and s.ua.holding
                    and s.ua.status != "connecting"
                    and now - s.last_seen > self.release_after
                ):
                    log.info("web session of %s: no page open, its OPC UA session released", s.user or "anonymous")
                    await s.ua.release()

    def _refused(self, s: WebSession, problem: str) -> None:
        """The server no longer takes the password of ``s``: end it, the page asks for a login."""
        s.ended_because = problem
        self._later(self._end(s))

    async def close(self) -> None:
        self.closing.set()
        for s in list(self.sessions.values()):
            await self._end(s)
        if self._reaper is not None:
            self._reaper.cancel()

    # requests --------------------------------------------------------------------------------

    async def _checked(self, request: Request) -> tuple[WebSession, dict[str, Any]] | Response:
        """The session and JSON body of a state-changing request, or the refusal."""
        s = self._by_cookie(request)
        if s is None:
            return JSONResponse({"error": "session expired", "expired": True}, status_code=401)
        token = request.headers.get("x-csrf-token", "")
        if not secrets.compare_digest(token.encode(), s.csrf.encode()):
            log.warning("web: refused a request to %s without a valid CSRF token", request.url.path)
            return JSONResponse({"error": "missing or wrong CSRF token"}, status_code=403)
        try:
            body = await request.json()
        except (ValueError, UnicodeDecodeError):
            return JSONResponse({"error": "the request body must be JSON"}, status_code=400)
        except RecursionError:
            return JSONResponse({"error": "the request body is nested too deeply"}, status_code=400)
        if not isinstance(body, dict):
            return JSONResponse({"error": "the request body must be a JSON object"}, status_code=400)
        return s, body

    def _page(self, template: str) -> str:
        """index.html with each view's stylesheet and module in the companions' order (the modules run
        after app.js, before the page opens its session: they register how their parts are drawn)."""
        tags = [
            f'<link rel="stylesheet" href="/views/{html.escape(n)}">' for n in self._view_files if n.endswith(".css")
        ]
        tags += [
            f'<script type="module" src="/views/{html.escape(n)}"></script>'
            for n in self._view_files
            if n.endswith(".js")
        ]
        return template.replace("<!-- companion views -->", "\n".join(tags))

    async def index(self, request: Request) -> Response:
        # The page asks for its session (/api/session) with the token it keeps, or gets a new one.
        return HTMLResponse(self._index, headers=_SECURITY_HEADERS)

    async def view_file(self, request: Request) -> Response:
        """A companion's web view module or stylesheet (only those the companions declare)."""
        name = request.path_params["name"]
        file = self._view_files.get(name)
        if file is None:
            return Response("not found", status_code=404, media_type="text/plain")
        media = "text/javascript" if name.endswith(".js") else "text/css"
        return Response(file.read_bytes(), media_type=f"{media}; charset=utf-8", headers=_SECURITY_HEADERS)

    async def session_info(self, request: Request) -> Response:
        s = self._session(request)
        fresh = s is None
        if s is None:
            s = self._new_session()
        response = JSONResponse({"csrf": s.csrf, "user": s.user, "fresh": fresh, "server": self.url})
        return self._set_cookie(response, s) if fresh else response

    async def login(self, request: Request) -> Response:
        checked = await self._checked(request)
        if isinstance(checked, Response):
            return checked
        s, body = checked
        user, password = body.get("user"), body.get("password")
        if not isinstance(user, str) or not user or not isinstance(password, str):
            return JSONResponse({"error": "user name and password are required"}, status_code=400)
        ua = self.places.new_login(s, user, password)
        if not await self.places.login_room(s, ua):
            return JSONResponse({"error": self.places.busy_text(), "code": "BadTooManySessions"}, status_code=503)
        try:
            await ua.connect()
        except Exception as exc:
            await ua.close()
            self.places.resume_later(s)
            return self._login_failed(user, exc)
        log.info("web login of %s", user)
        await self._end(s)
        fresh = self._new_session()  # a new id and CSRF token after every login
        fresh.ua, fresh.user = ua, user
        ua.on_identity_refused = lambda exc: self._refused(fresh, ua.problem)
        return self._set_cookie(JSONResponse({"user": user, "csrf": fresh.csrf}), fresh)

    def _login_failed(self, user: str, exc: Exception) -> Response:
        if isinstance(exc, CallFailed):
            log.info("web login of %s refused: %s", user, exc.name)
            return JSONResponse({"error": login_refusal(exc), "code": exc.name}, status_code=401)
        if isinstance(exc, TimeoutError):
            log.info("web login of %s: no answer from the server in time", user)
            problem = "the server did not check the login in time (it slows logins down after failed attempts)"
            return JSONResponse({"error": f"{problem}; try again in a minute", "code": "BadTimeout"}, status_code=503)
        log.info("web login of %s failed: server unreachable (%s)", user, type(exc).__name__)
        return JSONResponse({"error": f"the OPC UA server {self.url} cannot be reached"}, status_code=503)

    async def logout(self, request: Request) -> Response:
        checked = await self._checked(request)
        if isinstance(checked, Response):
            return checked
        s, _ = checked
        log.info("web logout of %s", s.user or "anonymous")
        await self._end(s)
        fresh = self._new_session()
        return self._set_cookie(JSONResponse({"user": None, "csrf": fresh.csrf}), fresh)

    async def events(self, request: Request) -> Response:
        s = self._session(request)
        if s is None:
            return JSONResponse({"error": "session expired", "expired": True}, status_code=401)
        s.streams += 1  # a page opening: its session is neither released nor ended meanwhile
        try:
            ua = await self.places.ua(s)
        except BaseException:
            s.streams -= 1
            raise
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        ua.listeners.add(queue.put_nowait)
        started = False

        def page_gone() -> None:
            s.streams -= 1
            s.last_seen = time.monotonic()
            ua.listeners.discard(queue.put_nowait)

        async def stream() -> AsyncIterator[str]:
            nonlocal started
            started = True
            try:
                yield _sse({"type": "snapshot", **ua.snapshot()})
                closing = asyncio.ensure_future(self.closing.wait())
                getter: asyncio.Future[dict[str, Any]] | None = None
                try:
                    while s.id in self.sessions and s.ua is ua:
                        getter = asyncio.ensure_future(queue.get())
                        done, _ = await asyncio.wait(
                            {getter, closing}, timeout=HEARTBEAT, return_when=asyncio.FIRST_COMPLETED
                        )
                        if closing in done:
                            getter.cancel()
                            return
                        if getter in done:
                            batch = [getter.result()]
                            while not queue.empty():
                                batch.append(queue.get_nowait())
                            yield "".join(_sse(m) for m in batch)
                        else:
                            getter.cancel()
                            yield ": keep-alive\n\n"
                    yield _sse({"type": "expired", "reason": s.ended_because})
                finally:
                    closing.cancel()
                    if getter is not None:
                        getter.cancel()
            finally:
                page_gone()

        headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
        return _PageStream(stream(), lambda: None if started else page_gone(), headers)

    async def _act(self, request: Request, action: str) -> Response:
        checked = await self._checked(request)
        if isinstance(checked, Response):
            return checked
        s, body = checked
        ua = await self.places.ua(s)
        try:
            if action == "call":
                args = body.get("args", [])
                if not isinstance(args, list):
                    return JSONResponse({"error": "args must be a list"}, status_code=400)
                return JSONResponse(await ua.call(str(body.get("key", "")), args))
            directory, path = str(body.get("directory", "")), str(body.get("path", ""))
            if action == "file":
                return JSONResponse({"content": await ua.programs.read(directory, path)})
            if action == "upload":
                content = str(body.get("content", "")).encode("utf-8")
                if len(content) > MAX_UPLOAD or not path or "/" in path:
                    return JSONResponse({"error": "a file name and at most 1 MB of text"}, status_code=400)
                await ua.programs.write(directory, path, content)
            elif action == "delete":
                await ua.programs.delete(directory, path)
            return JSONResponse({"good": True, "code": "Good", "meaning": ""})
        except UnknownKey as exc:
            return JSONResponse({"error": f"unknown {exc}"}, status_code=404)
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        except CallFailed as exc:
            return JSONResponse({"good": False, "code": exc.name, "meaning": exc.doc})
        except (OSError, TimeoutError, ConnectionError) as exc:
            return JSONResponse(
                {
                    "good": False,
                    "code": "BadServerNotConnected",
                    "meaning": f"the OPC UA server cannot be reached ({type(exc).__name__})",
                }
            )

    async def call(self, request: Request) -> Response:
        return await self._act(request, "call")

    async def history(self, request: Request) -> Response:
        """GET ?hours=N[&width=W][&since=T]: the history view's data (uacell.web.history), read as this
        session's user: ``width`` pixel columns per trend, and with ``since`` (the ``end`` of the
        answer before) only what is new since then."""
        s = self._session(request)
        if s is None:
            return JSONResponse({"error": "session expired", "expired": True}, status_code=401)
        query = request.query_params
        try:
            hours = float(query.get("hours", "8"))
            width = int(query.get("width", str(HISTORY_WIDTH)))
            since = float(query["since"]) if "since" in query else None
        except ValueError:
            return JSONResponse({"error": "hours, width and since must be numbers"}, 400)
        if not 0 < hours <= MAX_HISTORY_HOURS:
            return JSONResponse({"error": f"hours must be more than 0 and at most {MAX_HISTORY_HOURS:g}"}, 400)
        if since is not None and not math.isfinite(since):
            return JSONResponse({"error": "since must be a time in seconds since the epoch"}, 400)
        try:
            return JSONResponse(await (await self.places.ua(s)).history(hours, since=since, width=width))
        except CallFailed as exc:
            return JSONResponse({"error": f"{exc.name}: {exc.doc}", "code": exc.name}, status_code=409)
        except (OSError, TimeoutError, ConnectionError) as exc:
            return JSONResponse({"error": f"the OPC UA server cannot be reached ({type(exc).__name__})"}, 503)

    async def file(self, request: Request) -> Response:
        return await self._act(request, "file")

    async def upload(self, request: Request) -> Response:
        return await self._act(request, "upload")

    async def delete(self, request: Request) -> Response:
        return await self._act(request, "delete")


class _PageStream(StreamingResponse):
    """An event stream that says when it was never read (the browser left before the first byte)."""

    def __init__(self, content: AsyncIterator[str], unread: Callable[[], None], headers: dict[str, str]) -> None:
        super().__init__(content, media_type="text/event-stream", headers=headers)
        self._unread = unread

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._unread()


_SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'",
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def _sse(message: dict[str, Any]) -> str:
    return f"data: {json.dumps(message, separators=(',', ':'))}\n\n"
