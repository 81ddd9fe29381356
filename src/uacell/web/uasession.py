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
import dataclasses
import enum
import logging
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from asyncua import Client, Node, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.ua.uaerrors import UaStatusCodeError

from uacell.companion import WebView
from uacell.errors import login_refusal as refused_login
from uacell.web.discovery import Cell, discover, list_files
from uacell.web.history import WIDTH, cell_history

log = logging.getLogger(__name__)

APPLICATION_URI = "urn:uacell:web"
RETRY_SECONDS = 2.0
LOGIN_TIMEOUT = 45.0  # seconds a server may take to check a login (and a dead connection may go unnoticed)
EVENTS_KEPT = 30
CONNECTS_AT_ONCE = 8  # OPC UA connections the HMI opens at once (handshake and activation)
_AUDIT_UPDATE_STATE = ua.NodeId(ua.ObjectIds.AuditUpdateStateEventType)
_FILE_CHUNK = 60000


# The server refused who the session claims to be: retrying the same password cannot help (and each
# attempt is a failed login in the server's log and throttle).
IDENTITY_REFUSED = frozenset(
    {
        ua.StatusCodes.BadUserAccessDenied,
        ua.StatusCodes.BadIdentityTokenRejected,
        ua.StatusCodes.BadIdentityTokenInvalid,
    }
)


class SessionSlots:
    """The OPC UA sessions an HMI may hold on the server at once (``[web] ua_sessions``).

    A ``UaSession`` takes a slot before it connects and gives it back only once its client is
    disconnected and no connect of it is under way, so the server never holds more sessions of this
    HMI than there are slots, whatever the concurrency. ``take`` and ``give`` never await: checking
    and taking happen in one step of the event loop. ``on_free`` is told whenever a slot came free.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.holders: set[object] = set()
        self.on_free: Callable[[], None] | None = None
        self._freed = asyncio.Event()
        # Connections of one address that have not activated a session yet are what a server evicts
        # first ([limits] pending_per_address, 32 in uacell): the HMI opens only a few at once.
        self.connecting = asyncio.Semaphore(CONNECTS_AT_ONCE)

    def take(self, holder: object) -> bool:
        if holder in self.holders:
            return True
        if len(self.holders) >= self.capacity:
            return False
        self.holders.add(holder)
        return True

    def give(self, holder: object) -> None:
        if holder in self.holders:
            self.holders.discard(holder)
            self._freed.set()
            self._freed = asyncio.Event()
            if self.on_free is not None:
                self.on_free()

    async def wait_take(self, holder: object, timeout: float) -> bool:
        """``take``, waiting up to ``timeout`` seconds for a slot to come free."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not self.take(holder):
            remaining = deadline - loop.time()
            if remaining <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._freed.wait(), remaining)
        return True

    @property
    def free(self) -> int:
        return self.capacity - len(self.holders)


class Superseded(Exception):
    """A connect that finished after its session was released or closed: its client was disconnected."""


class UnknownKey(LookupError):
    """The page named a method or directory this cell does not have."""


class CallFailed(Exception):
    """An OPC UA request answered with a Bad status code."""

    def __init__(self, code: int, context: str = "") -> None:
        self.code = code
        name, doc = status_text(code)
        super().__init__(f"{context}: {name}" if context else name)
        self.name = name
        self.doc = doc


def login_refusal(exc: CallFailed) -> str:
    """What the login box says when the server refused a login: plain words for wrong credentials."""
    words = refused_login(exc.name)
    return f"{words[0].upper()}{words[1:]}" if words else f"{exc.name}: {exc.doc}"


def status_text(code: int) -> tuple[str, str]:
    """The status code's name and meaning, as OPC UA defines them."""
    name, doc = ua.status_codes.get_name_and_doc(code)
    return name, doc


@dataclass(frozen=True)
class Credentials:
    """How the HMI identifies itself to the server (its application instance certificate)."""

    certificate: Path
    private_key: Path
    server_certificate: Path | None = None  # pinned; None: taken from the server's endpoints


def jsonable(value: Any) -> Any:
    """An OPC UA value as JSON: texts as strings, NodeIds as strings, structures as objects."""
    if value is None or isinstance(value, bool | int | str):
        return value.value if isinstance(value, enum.Enum) else value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, ua.QualifiedName):
        return value.Name
    if isinstance(value, ua.NodeId):
        return value.to_string()
    if isinstance(value, ua.StatusCode):
        return value.name
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if dataclasses.is_dataclass(value):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return str(value)


_ALIASES = {290: ua.VariantType.Double, 294: ua.VariantType.DateTime, 884: ua.VariantType.ExtensionObject}


def to_variant(argument: ua.Argument, value: Any) -> ua.Variant:
    """A JSON value as the Variant ``argument`` asks for (ValueError says what does not fit)."""
    if argument.ValueRank >= 1:
        if not isinstance(value, list):
            raise ValueError(f"{argument.Name} must be a list")
        items = [_scalar(argument, v) for v in value]
        return ua.Variant(items, _variant_type(argument.DataType), is_array=True)
    return ua.Variant(_scalar(argument, value), _variant_type(argument.DataType))


def _variant_type(data_type: ua.NodeId) -> ua.VariantType:
    if data_type.NamespaceIndex == 0 and isinstance(data_type.Identifier, int):
        if 1 <= data_type.Identifier <= 25:
            return ua.VariantType(data_type.Identifier)
        if data_type.Identifier in _ALIASES:
            return _ALIASES[data_type.Identifier]
    if data_type in ua.enums_by_datatype or data_type == ua.NodeId(ua.ObjectIds.Enumeration):
        return ua.VariantType.Int32
    return ua.VariantType.ExtensionObject


def _scalar(argument: ua.Argument, value: Any) -> Any:
    vt = _variant_type(argument.DataType)
    name = argument.Name
    try:
        if vt == ua.VariantType.Boolean:
            if not isinstance(value, bool):
                raise ValueError
            return value
        if vt == ua.VariantType.Float:
            single = float(value)
            if not abs(single) <= FLOAT_MAX:  # also NaN: what a Float cannot hold is refused here
                raise ValueError
            return single
        if vt == ua.VariantType.Double:
            return float(value)
        if vt.name in _INT_RANGES:
            return _whole(vt.name, value)
        if vt == ua.VariantType.String:
            return str(value)
        if vt == ua.VariantType.LocalizedText:
            return ua.LocalizedText(str(value))
        if vt == ua.VariantType.ByteString:
            return bytes.fromhex(str(value))
        if vt == ua.VariantType.NodeId:
            return ua.NodeId.from_string(str(value))
        cls = ua.extension_objects_by_datatype.get(argument.DataType)
        if cls is None or not isinstance(value, dict):
            raise ValueError
        return _structure(cls, value)
    except (ValueError, TypeError, ua.UaError) as exc:
        reason = str(exc) if isinstance(exc, ValueError) and str(exc) else f"{value!r} is not a valid {vt.name}"
        raise ValueError(f"{name}: {reason}") from exc


FLOAT_MAX = 3.4028234663852886e38  # the largest finite single-precision number

_INT_RANGES = {
    name: (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2**bits - 1)
    for name, bits, signed in (
        ("SByte", 8, True),
        ("Byte", 8, False),
        ("Int16", 16, True),
        ("UInt16", 16, False),
        ("Int32", 32, True),
        ("UInt32", 32, False),
        ("Int64", 64, True),
        ("UInt64", 64, False),
    )
}


def _whole(type_name: str, item: Any) -> int:
    """A JSON number as a whole number that fits ``type_name`` (ValueError names the range)."""
    low, high = _INT_RANGES[type_name]
    try:
        whole = int(item) if isinstance(item, int) else int(float(item))
        fits = not isinstance(item, bool) and float(item) == whole
    except (ValueError, TypeError, OverflowError):
        fits = False
    if not fits:
        raise ValueError(f"{item!r} is not a whole number")
    if not low <= whole <= high:
        raise ValueError(f"{item!r} is outside {low}..{high} ({type_name})")
    return whole


def _structure(cls: type, value: dict[str, Any]) -> Any:
    """A structure from a JSON object, field by field (names compared without case)."""
    obj = cls()
    fields = {f.name.lower(): f for f in dataclasses.fields(obj)}
    for key, item in value.items():
        f = fields.get(str(key).lower())
        if f is None:
            raise ValueError(f"no field {key}")
        setattr(obj, f.name, _field(str(f.type), item))
    return obj


def _field(type_name: str, item: Any) -> Any:
    base = type_name.rsplit(".", 1)[-1].strip("'\"")
    if base in _INT_RANGES:
        return _whole(base, item)
    if base in ("Float", "Double"):
        return float(item)
    if base == "Boolean":
        if not isinstance(item, bool):
            raise ValueError(f"{item!r} is not true or false")
        return item
    if base == "String":
        return str(item)
    if base == "LocalizedText":
        return ua.LocalizedText(str(item))
    if base == "EUInformation" and isinstance(item, str):  # a unit given by its name, e.g. "ml"
        return ua.EUInformation(DisplayName=ua.LocalizedText(item), Description=ua.LocalizedText(item))
    cls = getattr(ua, base, None)
    if isinstance(cls, type) and dataclasses.is_dataclass(cls) and isinstance(item, dict):
        return _structure(cls, item)
    raise ValueError(f"{item!r} does not fit {base}")


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
        self._methods_task: asyncio.Task[None] | None = None
        self._methods_again = False
        self._modules_task: asyncio.Task[None] | None = None
        self._modules_again = False
        self._reconnect_task: asyncio.Task[None] | None = None
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
        server_cert = str(c.server_certificate) if c.server_certificate else None
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
        self._emit({"type": "snapshot", **self.snapshot()})

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
        await self.refresh_methods()
        await self.refresh_files()
        await self.refresh_modules()
        self.role = await self._read_role(client)

    async def _read_role(self, client: Client) -> str | None:
        """This session's role, as the server says it (None against a server without CurrentRole)."""
        if self.cell.role is None:
            return None
        with contextlib.suppress(Exception):
            value = await Node(client.uaclient, self.cell.role).read_value()
            return str(value) if value else None
        return None

    async def _lost(self, exc: Exception) -> None:
        if self.status == "released":
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
        self._generation += 1
        for task in (self._reconnect_task, self._methods_task, self._modules_task):
            if task is not None and not task.done():
                task.cancel()
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

    async def close(self) -> None:
        self._closed = True
        self._generation += 1
        for task in (self._reconnect_task, self._methods_task, self._modules_task):
            if task is not None and not task.done():
                task.cancel()
        client, self.client = self.client, None
        if client is not None:
            await _quietly_disconnect(client)
        self._settle()

    def _require(self) -> Client:
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
        return await cell_history(self._require(), self.cell, hours, since=since, width=width)

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
        self._emit({"type": "status", "status": self.status, "problem": self.problem})

    def _emit(self, message: dict[str, Any]) -> None:
        for listener in list(self.listeners):
            listener(message)

    def _value(self, node: ua.NodeId, value: Any) -> None:
        key = self._by_node.get(node)
        if key is None:
            return
        self.values[key] = self._pending[key] = jsonable(value)
        if key.endswith(("/TaskProgramName", "/CurrentState")):
            self._schedule_modules()
        if not self._flush_scheduled:
            self._flush_scheduled = True
            asyncio.get_running_loop().call_soon(self._flush)

    def _flush(self) -> None:
        self._flush_scheduled = False
        pending, self._pending = self._pending, {}
        if pending:
            self._emit({"type": "values", "values": pending})

    def _event(self, event: Any) -> None:
        source = getattr(event, "SourceNode", None)
        if getattr(event, "EventType", None) == _AUDIT_UPDATE_STATE:
            self._audit(event, source)
            return
        machine = self.cell.machines.get(source.to_string()) if isinstance(source, ua.NodeId) else None
        # The machine's LastTransitionReason is published before its event: its value now is this one's.
        reason = None
        if machine:
            reason = self.values.get(f"{machine}/LastTransitionReason/ValueAsText")
            reason = reason or self.values.get(f"{machine}/LastTransitionReason")
        entry = {
            "time": jsonable(getattr(event, "Time", None)),
            "machine": machine or jsonable(getattr(event, "SourceName", "")),
            "transition": jsonable(getattr(event, "Transition", None)),
            "from": jsonable(getattr(event, "FromState", None)),
            "to": jsonable(getattr(event, "ToState", None)),
            "message": jsonable(getattr(event, "Message", None)),
            "reason": reason,
            "source": jsonable(source),
            "from_id": jsonable(getattr(event, "FromState/Id", None)),
            "to_id": jsonable(getattr(event, "ToState/Id", None)),
            "user": None,  # set by the AuditUpdateStateEvent that follows when a call caused it
        }
        self.events.appendleft(entry)
        self._emit({"type": "event", "event": entry})

    def _audit(self, event: Any, source: Any) -> None:
        """Who caused a transition: the AuditUpdateStateEvent the server fires right after the
        TransitionEvent of a transition a method call caused (none for one that followed by itself)."""
        key = (
            jsonable(source),
            jsonable(getattr(event, "OldStateId", None)),
            jsonable(getattr(event, "NewStateId", None)),
        )
        for entry in self.events:  # newest first
            if entry["user"] is None and (entry["source"], entry["from_id"], entry["to_id"]) == key:
                entry["user"] = getattr(event, "ClientUserId", None) or "anonymous"  # null: an anonymous session
                entry["method"] = str(getattr(event, "SourceName", "") or "").removeprefix("Method/")
                self._emit({"type": "events", "events": list(self.events)})
                return

    def _executable_changed(self) -> None:
        if self._methods_task is not None and not self._methods_task.done():
            self._methods_again = True
            return
        self._methods_task = asyncio.get_running_loop().create_task(self._methods_loop())

    async def _methods_loop(self) -> None:
        while True:
            self._methods_again = False
            try:
                await self.refresh_methods()
            except Exception as exc:
                log.debug("reading UserExecutable failed: %s", exc)
            if not self._methods_again:
                return

    async def refresh_methods(self) -> None:
        """Read Executable and UserExecutable of every method in this session (its role's answer)."""
        client = self.client
        if client is None or not self.cell.methods:
            return
        keys = list(self.cell.methods)
        params = ua.ReadParameters()
        for key in keys:
            for attr in (ua.AttributeIds.Executable, ua.AttributeIds.UserExecutable):
                params.NodesToRead.append(ua.ReadValueId(NodeId=self.cell.methods[key].method, AttributeId=attr))
        results = await client.uaclient.read(params)
        state = {}
        for i, key in enumerate(keys):
            x, u = results[2 * i], results[2 * i + 1]
            state[key] = {
                "executable": bool(x.Value and x.Value.Value),
                "user_executable": bool(u.Value and u.Value.Value),
            }
        changed = {k: v for k, v in state.items() if self.methods.get(k) != v}
        self.methods.update(state)
        if changed:
            self._emit({"type": "methods", "methods": changed})

    async def refresh_files(self) -> None:
        client = self.client
        if client is None:
            return
        for key, directory in self.cell.directories.items():
            files = await list_files(client, directory)
            viewable = await self._may_read(client, files[0]["node"]) if files else True
            self.files[key] = [{"name": f["name"], "path": f["path"], "viewable": viewable} for f in files]
        self._emit({"type": "files", "files": self.files})

    async def _may_read(self, client: Client, file_node: ua.NodeId) -> bool:
        """Whether this user may read the directory's files: the server's UserExecutable of FileType's
        Read (every file of a directory is read under the same role)."""
        try:
            read = await Node(client.uaclient, file_node).get_child("0:Read")
            value = await read.read_attribute(ua.AttributeIds.UserExecutable)
            return bool(value.Value.Value)
        except Exception:  # no answer: let the server decide when the user tries
            return True

    def _schedule_modules(self) -> None:
        """Browse the TaskModules folders again soon; a request while a browse runs is kept, so a
        module loaded meanwhile is never missed."""
        if not self.cell.folders:
            return
        if self._modules_task is not None and not self._modules_task.done():
            self._modules_again = True
            return
        self._modules_task = asyncio.get_running_loop().create_task(self._modules_loop())

    async def _modules_loop(self) -> None:
        while True:
            self._modules_again = False
            await self.refresh_modules()
            if not self._modules_again:
                return

    async def refresh_modules(self) -> None:
        client = self.client
        if client is None:
            return
        with contextlib.suppress(Exception):
            for key, folder in self.cell.folders.items():
                refs = await Node(client.uaclient, folder).get_children_descriptions()
                self.modules[key] = sorted(r.BrowseName.Name for r in refs)
            self._emit({"type": "modules", "modules": self.modules})

    # what the user does ----------------------------------------------------------------------

    async def call(self, key: str, args: list[Any]) -> dict[str, Any]:
        """Call the method ``key`` with JSON ``args`` in this session; the server's answer as JSON."""
        self._require()
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
            self._schedule_modules()
            if outputs and isinstance(outputs[0], int):
                answer["status_name"] = ref.status.get(outputs[0], "")
        return answer

    async def _call(self, obj: ua.NodeId, method: ua.NodeId, inputs: list[ua.Variant], what: str) -> dict[str, Any]:
        client = self._require()
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

    async def _file_method(self, file_node: ua.NodeId, name: str, *inputs: ua.Variant) -> list[Any]:
        client = self._require()
        method = next(
            (
                r.NodeId
                for r in await Node(client.uaclient, file_node).get_children_descriptions()
                if r.BrowseName.Name == name
            ),
            None,
        )
        if method is None:
            raise CallFailed(ua.StatusCodes.BadMethodInvalid, name)
        request = ua.CallMethodRequest(ObjectId=file_node, MethodId=method, InputArguments=list(inputs))
        (result,) = await client.uaclient.call([request])
        if not result.StatusCode.is_good():
            raise CallFailed(result.StatusCode.value, name)
        return [v.Value for v in result.OutputArguments or []]

    async def _find_file(self, directory: str, path: str) -> ua.NodeId | None:
        client = self._require()
        node = self.cell.directories.get(directory)
        if node is None:
            raise UnknownKey(directory)
        return next((f["node"] for f in await list_files(client, node) if f["path"] == path), None)

    async def read_file(self, directory: str, path: str) -> str:
        node = await self._find_file(directory, path)
        if node is None:
            raise CallFailed(ua.StatusCodes.BadNotFound, path)
        (handle,) = await self._file_method(node, "Open", ua.Variant(1, ua.VariantType.Byte))
        h = ua.Variant(handle, ua.VariantType.UInt32)
        data = b""
        try:
            while True:
                (chunk,) = await self._file_method(node, "Read", h, ua.Variant(_FILE_CHUNK, ua.VariantType.Int32))
                if not chunk:
                    break
                data += chunk
        finally:
            with contextlib.suppress(CallFailed):
                await self._file_method(node, "Close", h)
        return data.decode("utf-8", errors="replace")

    async def write_file(self, directory: str, name: str, content: bytes) -> None:
        """Create ``name`` in the directory (or replace its content) through FileType methods."""
        node = await self._find_file(directory, name)
        if node is None:
            dir_node = self.cell.directories[directory]
            node, handle = await self._file_method(
                dir_node,
                "CreateFile",
                ua.Variant(name, ua.VariantType.String),
                ua.Variant(True, ua.VariantType.Boolean),
            )
        else:
            (handle,) = await self._file_method(node, "Open", ua.Variant(2 | 4, ua.VariantType.Byte))
        h = ua.Variant(handle, ua.VariantType.UInt32)
        try:
            for start in range(0, len(content), _FILE_CHUNK):
                chunk = content[start : start + _FILE_CHUNK]
                await self._file_method(node, "Write", h, ua.Variant(chunk, ua.VariantType.ByteString))
        finally:
            with contextlib.suppress(CallFailed):
                await self._file_method(node, "Close", h)
        log.info("%s wrote program file %s", self.user or "anonymous", name)
        await self.refresh_files()

    async def delete_file(self, directory: str, path: str) -> None:
        node = await self._find_file(directory, path)
        if node is None:
            raise CallFailed(ua.StatusCodes.BadNotFound, path)
        await self._file_method(self.cell.directories[directory], "Delete", ua.Variant(node, ua.VariantType.NodeId))
        log.info("%s deleted program file %s", self.user or "anonymous", path)
        await self.refresh_files()


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
        self.session._executable_changed()
