"""One web user's OPC UA session: their identity, their subscriptions, their calls.

Everything the page shows comes from OPC UA subscriptions of this session (values, ``Executable``
of every method, TransitionEvents and the AuditUpdateStateEvents that name who caused them);
``UserExecutable`` is read back by this session whenever an ``Executable`` changes, so what the page
enables is what the server says this user may do now. Calls are made with this session, so roles,
locks and the audit trail are the server's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Client, Node, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.ua.uaerrors import UaStatusCodeError

from uacell.binding.web_discovery import Cell
from uacell.core.companion import WebView
from uacell.web.discovery import discover
from uacell.web.errors import CallFailed, UnknownKey, login_refusal, status_text
from uacell.web.event_entries import attribute, transition_entry
from uacell.web.history import WIDTH, cell_history
from uacell.web.session_files import ProgramFiles
from uacell.web.session_refresh import Refresher
from uacell.web.slots import SessionSlots
from uacell.web.values import jsonable, to_variant

__all__ = [  # what the HMI's other modules (and tests) take from here
    "CallFailed",
    "CellCache",
    "Credentials",
    "SessionSlots",
    "UaSession",
    "UnknownKey",
    "jsonable",
    "login_refusal",
    "to_variant",
]

log = logging.getLogger(__name__)

APPLICATION_URI = "urn:uacell:web"
RETRY_SECONDS = 2.0
LOGIN_TIMEOUT = 45.0  # seconds a server may take to check a login (and a dead connection may go unnoticed)
EVENTS_KEPT = 30
IDENTITY_CHECK_SECONDS = 2.0  # how often a logged-in session asks the server who it is (decision 103)
_AUDIT_UPDATE_STATE = ua.NodeId(ua.ObjectIds.AuditUpdateStateEventType)


# The server refused who the session claims to be: retrying the same password cannot help (and each
# attempt is a failed login in the server's log and throttle).
IDENTITY_REFUSED = frozenset(
    {
        ua.StatusCodes.BadUserAccessDenied,
        ua.StatusCodes.BadIdentityTokenRejected,
        ua.StatusCodes.BadIdentityTokenInvalid,
    }
)


class Superseded(Exception):
    """A connect that finished after its session was released or closed: its client was disconnected."""


@dataclass(frozen=True)
class Credentials:
    """How the HMI identifies itself to the server (its application instance certificate)."""

    certificate: Path
    private_key: Path
    # pinned (a file), or what the server beside the HMI sends now (its certificate changes with a GDS's
    # ApplyChanges, not with the file); None: taken from the server's endpoints
    server_certificate: Path | Callable[[], bytes] | None = None


Listener = Callable[[dict[str, Any]], None]


class CellCache:
    """The cell as found by one session, reused by the others of the same HMI (browsing takes a while).

    Found again whenever a session had lost the server: it may have restarted with another cell.
    """

    def __init__(self, views: Sequence[WebView] = ()) -> None:
        self.views = tuple(views)  # what the page shows (the companions' web views)
        self.cell: Cell | None = None
        self._lock = asyncio.Lock()

    async def get(self, client: Client) -> Cell:
        async with self._lock:
            if self.cell is None:
                # The server's structures (PackML parameters, counts, alarms) for decoding and encoding.
                await client.load_data_type_definitions()
                self.cell = await discover(client, self.views)
            return self.cell

    def forget(self) -> None:
        self.cell = None


class UaSession:
    """A web user's OPC UA session; ``connect()`` raises CallFailed when the server refuses them."""

    def __init__(
        self,
        url: str,
        credentials: Credentials,
        user: str | None = None,
        password: str | None = None,
        cache: CellCache | None = None,
    ) -> None:
        self.url = url
        self.cache = cache or CellCache()
        self.credentials = credentials
        self.user = user
        self._password = password
        self.client: Client | None = None
        self.cell = Cell()
        self.status = "connecting"
        self.problem = ""
        self.values: dict[str, Any] = {}
        self.methods: dict[str, dict[str, bool]] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=EVENTS_KEPT)
        self.files: dict[str, list[dict[str, Any]]] = {}
        self.modules: dict[str, list[str]] = {}
        self.role: str | None = None
        self.listeners: set[Listener] = set()
        self._pending: dict[str, Any] = {}
        self._flush_scheduled = False
        # Executable and UserExecutable of the methods, the TaskModules folders: read again on changes.
        self.refresher = Refresher(self)
        self.programs = ProgramFiles(self)  # a robot controller's program files
        self._reconnect_task: asyncio.Task[None] | None = None
        self._identity_task: asyncio.Task[None] | None = None
        self._closed = False
        self._by_node: dict[ua.NodeId, str] = {}
        # The slot this session holds while it has (or makes) an OPC UA session; None: not counted.
        self.slots: SessionSlots | None = None
        self._generation = 0  # release() and close() move it on: a connect under way then gives up
        self._connecting = 0
        # Called once when the server stops accepting this user's password (changed or removed while
        # the web session lived): the HMI ends the web session and asks for a new login.
        self.on_identity_refused: Callable[[CallFailed], None] | None = None

    # connection ------------------------------------------------------------------------------

    async def _new_client(self) -> Client:
        # The client's health probe starts with CreateSession, before the login is checked; a server
        # that slows down logins after failed attempts (uacell: up to 20 s) must not look dead meanwhile.
        # A server that goes away closes the TCP connection, which is noticed at once anyway.
        client = Client(self.url, timeout=LOGIN_TIMEOUT, watchdog_intervall=LOGIN_TIMEOUT)
        client.application_uri = APPLICATION_URI
        client.name = client.description = "uacell web HMI"
        client.session_timeout = 60000
        if self.user is not None:
            client.set_user(self.user)
            client.set_password(self._password or "")
        c = self.credentials
        pinned = c.server_certificate
        server_cert = pinned() if callable(pinned) else str(pinned) if pinned else None
        await client.set_security(
            SecurityPolicyBasic256Sha256,
            str(c.certificate),
            str(c.private_key),
            server_certificate=server_cert,
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )
        return client

    async def connect(self) -> None:
        generation = self._generation
        self._connecting += 1
        try:
            await self._connect(generation)
        finally:
            self._connecting -= 1
            self._settle()

    async def _connect(self, generation: int) -> None:
        client = await self._new_client()
        try:
            if self.slots is None:
                await client.connect()
            else:
                async with self.slots.connecting:
                    await client.connect()
        except UaStatusCodeError as exc:
            raise CallFailed(exc.code, "connect") from None
        except BaseException:
            client.disconnect_socket()  # cancelled or failed half-way: the server sees the connection go
            raise
        if generation != self._generation:
            await _quietly_disconnect(client)
            raise Superseded
        self.client = client
        try:
            await self._prepare(client)
            if generation != self._generation:
                raise Superseded
        except BaseException:
            if self.client is client:
                self.client = None
            await _quietly_disconnect(client)
            raise
        client.connection_lost_callback = self._lost
        self.status = "connected"
        self.problem = ""
        self.emit({"type": "snapshot", **self.snapshot()})
        if self.user is not None and self.cell.user is not None:
            self._identity_task = asyncio.get_running_loop().create_task(self._watch_identity(client, generation))

    def _settle(self) -> None:
        """Give the slot back once this session holds no OPC UA session and makes none."""
        if self.slots is None or self.client is not None or self._connecting:
            return
        if self._closed or self.status in ("released", "busy", "login-required"):
            self.slots.give(self)

    async def _prepare(self, client: Client) -> None:
        self.cell = await self.cache.get(client)
        self._by_node = {node: key for key, node in self.cell.variables.items()}
        self.values = {}
        values = await client.create_subscription(50, _Handler(self))
        nodes = [Node(client.uaclient, n) for n in self.cell.variables.values()]
        if nodes:
            await values.subscribe_data_change(nodes, queuesize=10)
        await values.subscribe_events(
            Node(client.uaclient, ua.NodeId(ua.ObjectIds.Server)),
            [
                Node(client.uaclient, ua.NodeId(ua.ObjectIds.TransitionEventType)),
                Node(client.uaclient, _AUDIT_UPDATE_STATE),
            ],
        )
        executable = await client.create_subscription(50, _ExecutableHandler(self))
        methods = [Node(client.uaclient, m.method) for m in self.cell.methods.values()]
        if methods:
            await executable.subscribe_data_change(methods, attr=ua.AttributeIds.Executable)
        await self.refresher.refresh_methods()
        await self.programs.refresh()
        await self.refresher.refresh_modules()
        self.role = await self._read_role(client)

    async def _read_role(self, client: Client) -> str | None:
        """This session's role, as the server says it (None against a server without CurrentRole)."""
        if self.cell.role is None:
            return None
        with contextlib.suppress(Exception):
            value = await Node(client.uaclient, self.cell.role).read_value()
            return str(value) if value else None
        return None

    async def _watch_identity(self, client: Client, generation: int) -> None:
        """Decision 103: the server may end a user's login while the session goes on, as anonymous
        (decision 99: ``users.toml`` changed). Every few seconds the session reads who it is; when it is
        no longer its user, it activates again with the password the web user logged in with: the role
        the server grants now, or, when the password no longer works, "login-required"."""
        assert self.cell.user is not None
        node = Node(client.uaclient, self.cell.user)
        while generation == self._generation and self.client is client:
            await asyncio.sleep(IDENTITY_CHECK_SECONDS)
            try:
                user = await node.read_value()
            except Exception:  # the connection is in trouble: _lost says so
                continue
            if user != self.user and generation == self._generation and self.client is client:
                await self._activate_again(client)

    async def _activate_again(self, client: Client) -> None:
        log.info("web session of %s: the server ended its login; activating it again", self.user)
        try:
            await client.activate_session(username=self.user, password=self._password or "")
        except UaStatusCodeError as exc:
            self.client = None  # the OPC UA session goes; the web user logs in again
            refused = self.identity_refused(CallFailed(exc.code, "activate"))
            await _quietly_disconnect(client)
            if not refused:
                self.fail(f"the server refused the session: {ua.StatusCode(exc.code).name}")
            return
        self.role = await self._read_role(client)
        await self.refresher.refresh_methods()
        self.emit({"type": "snapshot", **self.snapshot()})

    async def _lost(self, exc: Exception) -> None:
        if self.status in ("released", "login-required"):
            return
        log.info("web session of %s lost the server: %s", self.user or "anonymous", exc)
        self.cache.forget()
        self.fail(f"the OPC UA server {self.url} cannot be reached")

    def fail(self, problem: str) -> None:
        """Say ``problem`` to the page and keep trying to connect again."""
        if self._closed:
            return
        self.status = "unreachable"
        self.problem = problem
        self.announce()
        if self._reconnect_task is None or self._reconnect_task.done():
            self._reconnect_task = asyncio.get_running_loop().create_task(self._reconnect())

    def identity_refused(self, exc: CallFailed) -> bool:
        """True (and the page told, retries stopped) when ``exc`` refuses this session's user."""
        if self.user is None or exc.code not in IDENTITY_REFUSED:
            return False
        log.info("web session of %s: the server no longer accepts its password (%s)", self.user, exc.name)
        self._closed = True
        self._settle()
        self.status = "login-required"
        self.problem = f"The server no longer accepts the password of {self.user} ({exc.name}): log in again"
        self.announce()
        if self.on_identity_refused is not None:
            self.on_identity_refused(exc)
        return True

    @property
    def holding(self) -> bool:
        """Whether this web session holds (or is trying to hold) an OPC UA session on the server."""
        return not self._closed and self.status not in ("released", "busy", "login-required")

    async def release(self) -> None:
        """Give the server its session back while no page is open; ``resume()`` makes a new one."""
        self._stop()
        client, self.client = self.client, None
        self.status, self.problem = "released", ""
        if client is not None:
            await _quietly_disconnect(client)
        self._settle()

    def wait_for_place(self, problem: str) -> None:
        """No slot (or no session on the server) for this session now: say "busy"; the HMI resumes it
        when a place comes free."""
        self.status, self.problem = "busy", problem
        self.announce()
        self._settle()

    async def resume(self) -> None:
        """Connect again after ``release()`` (or after the HMI was busy); failures as in ``connect()``.
        Nothing to do while a connect of this session is under way or it is connected."""
        if self._connecting or self.status == "connected":
            return
        self.status = "connecting"
        try:
            await self.connect()
        except Superseded:
            return
        except CallFailed as exc:
            if exc.code == ua.StatusCodes.BadTooManySessions:  # the server's own limit: wait as for a slot
                log.info("web: the server %s has no session free for the HMI now", self.url)
                self.wait_for_place(f"the OPC UA server has no session free now ({exc.name}); waiting for one")
            elif not self.identity_refused(exc):
                log.warning("web: the server %s refused the HMI's session: %s", self.url, exc.name)
                self.fail(f"the server refused the HMI's session: {exc.name} ({exc.doc})")
        except Exception as exc:
            log.info("web: cannot reach %s: %s", self.url, exc)
            self.fail(f"the OPC UA server {self.url} cannot be reached")

    async def _reconnect(self) -> None:
        old, self.client = self.client, None
        if old is not None:
            with contextlib.suppress(Exception):
                await old.disconnect()
        while not self._closed:
            await asyncio.sleep(RETRY_SECONDS)
            try:
                await self.connect()
            except Superseded:
                return
            except CallFailed as exc:
                if self.identity_refused(exc):
                    return
                self.problem = f"the server refused the session: {exc.name}"
                self.announce()
                continue
            except Exception as exc:  # the server is still away (or went away again while we set up)
                log.debug("reconnecting to %s failed: %r", self.url, exc)
                continue
            log.info("web session of %s reconnected", self.user or "anonymous")
            return

    def _stop(self) -> None:
        """A connect under way gives up; what reads, reconnects or watches for this session ends."""
        self._generation += 1
        self.refresher.cancel()
        for task in (self._reconnect_task, self._identity_task):
            if task is not None and not task.done() and task is not asyncio.current_task():
                task.cancel()

    async def close(self) -> None:
        self._closed = True
        self._stop()
        client, self.client = self.client, None
        if client is not None:
            await _quietly_disconnect(client)
        self._settle()

    def require(self) -> Client:
        if self.status == "login-required":
            raise CallFailed(ua.StatusCodes.BadUserAccessDenied, "log in first")
        if self.status == "busy":
            raise CallFailed(ua.StatusCodes.BadTooManySessions, self.problem)
        if self.client is None or self.status != "connected":
            raise CallFailed(ua.StatusCodes.BadServerNotConnected, "not connected")
        return self.client

    async def history(self, hours: float, *, since: float | None = None, width: int = WIDTH) -> dict[str, Any]:
        """The history view of the last ``hours`` (uacell.web.history), through this session: whole, or
        what came after ``since``."""
        return await cell_history(self.require(), self.cell, hours, since=since, width=width)

    # what the page sees ----------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "problem": self.problem,
            "user": self.user,
            "role": self.role,
            "layout": self.cell.layout,
            "values": self.values,
            "methods": self.methods,
            "events": list(self.events),
            "files": self.files,
            "modules": self.modules,
        }

    def announce(self) -> None:
        """Tell open pages the session's status and problem as they are now."""
        self.emit({"type": "status", "status": self.status, "problem": self.problem})

    def emit(self, message: dict[str, Any]) -> None:
        for listener in list(self.listeners):
            listener(message)

    def _value(self, node: ua.NodeId, value: Any) -> None:
        key = self._by_node.get(node)
        if key is None:
            return
        self.values[key] = self._pending[key] = jsonable(value)
        if self.cell.rebrowse and key.endswith(self.cell.rebrowse):
            self.refresher.schedule_modules()
        if not self._flush_scheduled:
            self._flush_scheduled = True
            asyncio.get_running_loop().call_soon(self._flush)

    def _flush(self) -> None:
        self._flush_scheduled = False
        pending, self._pending = self._pending, {}
        if pending:
            self.emit({"type": "values", "values": pending})

    def _event(self, event: Any) -> None:
        if getattr(event, "EventType", None) == _AUDIT_UPDATE_STATE:
            if attribute(self.events, event) is not None:
                self.emit({"type": "events", "events": list(self.events)})
            return
        source = getattr(event, "SourceNode", None)
        machine = self.cell.machines.get(source.to_string()) if isinstance(source, ua.NodeId) else None
        # The machine's LastTransitionReason is published before its event: its value now is this one's.
        reason = None
        if machine:
            reason = self.values.get(f"{machine}/LastTransitionReason/ValueAsText")
            reason = reason or self.values.get(f"{machine}/LastTransitionReason")
        entry = transition_entry(event, machine, reason)
        self.events.appendleft(entry)
        self.emit({"type": "event", "event": entry})

    # what the user does ----------------------------------------------------------------------

    async def call(self, key: str, args: list[Any]) -> dict[str, Any]:
        """Call the method ``key`` with JSON ``args`` in this session; the server's answer as JSON."""
        self.require()
        ref = self.cell.methods.get(key)
        if ref is None:
            raise UnknownKey(key)
        if len(args) > len(ref.arguments):
            raise ValueError(f"{key} takes {len(ref.arguments)} arguments")
        inputs = [to_variant(a, v) for a, v in zip(ref.arguments, args, strict=False)]
        answer = await self._call(ref.object, ref.method, inputs, key)
        outputs = answer["outputs"]
        if ref.status is not None:
            # An operation (loading or unloading a module) may change no state or program name:
            # browse the modules again.
            self.refresher.schedule_modules()
            if outputs and isinstance(outputs[0], int):
                answer["status_name"] = ref.status.get(outputs[0], "")
        return answer

    async def _call(self, obj: ua.NodeId, method: ua.NodeId, inputs: list[ua.Variant], what: str) -> dict[str, Any]:
        client = self.require()
        request = ua.CallMethodRequest(ObjectId=obj, MethodId=method, InputArguments=inputs)
        (result,) = await client.uaclient.call([request])
        code = result.StatusCode.value
        name, doc = status_text(code)
        outputs = [jsonable(v.Value) for v in result.OutputArguments or []]
        answer: dict[str, Any] = {"good": result.StatusCode.is_good(), "code": name, "meaning": doc, "outputs": outputs}
        arg_results = [r.name for r in result.InputArgumentResults or [] if not r.is_good()]
        if arg_results:
            answer["argument_results"] = arg_results
        log.info("%s called %s: %s", self.user or "anonymous", what, name)
        return answer


async def _quietly_disconnect(client: Client) -> None:
    """CloseSession (the server forgets the session before it answers), then the channel and socket."""
    try:
        await client.disconnect()
    except Exception:
        client.disconnect_socket()


class _Handler:
    def __init__(self, session: UaSession) -> None:
        self.session = session

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.session._value(node.nodeid, val)

    def event_notification(self, event: Any) -> None:
        self.session._event(event)


class _ExecutableHandler:
    def __init__(self, session: UaSession) -> None:
        self.session = session

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.session.refresher.executable_changed()
