"""One OPC UA client connection to a PLC, shared by every part on that endpoint with the same
options (asyncua ``Client``).

The link connects in the background and reconnects with backoff (0.5 s doubling to 2 s) whenever
the connection is lost, so uacell serves whether or not the PLC is there. Parts register the tags
they watch; on every (re)connection the link reads them once and then either subscribes to them
(one subscription per link at ``interval``) or, in ``poll`` mode, reads them all in one Read request
every ``interval``; it calls each part's listener with every new value and with the connection
state. Reads and writes go straight to the PLC (no queue, no replay): a lost connection raises
``CommunicationError``. The channel may be signed and encrypted (``security``, with uacell's client
certificate and key as files) and the session may log in as a user whose password comes from an
owner-only file or the environment (``uacell.core.secret_file``), never from the cell file.

A PLC killed or out of reach is expected: uacell says it once (``Listeners._report_lost``), and the
records asyncua's client makes of it ("Publish iteration crashed", "close_secure_channel raised"
with a traceback) are one DEBUG line each (``quiet_client``); any other exception keeps its ERROR.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from uacell.core.background import stop_task
from uacell.core.logs import exception_of, quiet_expected
from uacell.core.secret_file import SecretError, read_secret
from uacell.gateway.errors import CommunicationError
from uacell.gateway.link import Listeners, StateListener, ValueListener, network_error
from uacell.gateway.pool import SharedPool
from uacell.gateway.retry import keep_trying

log = logging.getLogger(__name__)

# The tags' sampling interval: 0, the fastest the PLC's server supports (exception-based where it can
# be). asyncua's own default is 50 ms, which a server samples at: 25 ms of delay on average before
# the publishing interval even starts (docs/performance.md, "Gateway").
SAMPLING = 0.0
PASSWORD_ENV = "UACELL_PLC_PASSWORD"  # the default environment variable of a PLC user's password
POLICIES = ("Basic256Sha256", "Aes128Sha256RsaOaep", "Aes256Sha256RsaPss")
MODES = ("Sign", "SignAndEncrypt")
# the driver settings ``link_options`` reads
LINK_SETTINGS = (
    "endpoint", "security", "certificate", "private_key", "username", "password_file", "password_env",
    "mode", "interval", "publishing_interval", "timeout",
)  # fmt: skip


# asyncua's client loggers (by exact name: a logger's filters do not apply to its children)
CLIENT_LOGGERS = (
    "asyncua.client.client",
    "asyncua.client.ua_client.UaClient",
    "asyncua.client.ua_client.UASocketProtocol",
    "asyncua.client.ua_session.UaSession",
    "asyncua.common.subscription",
)
# what a server gone or going away answers
LOSS_CODES = frozenset(
    getattr(ua.StatusCodes, name)
    for name in (
        "BadConnectionClosed", "BadSecureChannelClosed", "BadSecureChannelIdInvalid", "BadTcpSecureChannelUnknown",
        "BadSessionClosed", "BadSessionIdInvalid", "BadTimeout", "BadRequestTimeout", "BadServerNotConnected",
        "BadNotConnected", "BadConnectionRejected", "BadCommunicationError", "BadNoCommunication", "BadShutdown",
        "BadServerHalted",
    )
)  # fmt: skip
# asyncua's warnings when it closes what the server already closed
_CLOSED = (
    "close_session was called but connection is closed",
    "close_secure_channel was called but connection is closed",
)


def server_lost(exc: BaseException | None) -> bool:
    """``exc`` says the server (the PLC) went away or cannot be reached."""
    return network_error(exc) or (isinstance(exc, ua.UaStatusCodeError) and exc.code in LOSS_CODES)


def _expected(record: logging.LogRecord) -> bool:
    exc = exception_of(record)
    return server_lost(exc) if exc is not None else str(record.msg).startswith(_CLOSED)


def quiet_client() -> None:
    """asyncua's client records of a lost server become DEBUG lines (``uacell.core.logs.ExpectedFaults``)."""
    quiet_expected("plc-lost", CLIENT_LOGGERS, _expected)


@dataclass(frozen=True)
class LinkOptions:
    """How to reach one PLC: links are shared by parts whose options are equal."""

    endpoint: str
    security: str = "None"  # "None", or "<policy>,<mode>" (POLICIES, MODES)
    certificate: str = ""  # uacell's client certificate for this PLC (PEM or DER), with security
    private_key: str = ""  # ... and its private key
    username: str = ""  # "" : an anonymous session
    password: str = field(default="", repr=False)
    mode: str = "subscribe"  # or "poll"
    interval: float = 0.02  # seconds: the subscription's publishing interval, or the poll period
    # seconds a request may take, and the PLC may leave the keep-alive unanswered before it is lost
    timeout: float = 2.0


def link_options(part: str, settings: Mapping[str, Any]) -> LinkOptions:
    """The link options of a driver's settings, checked; a ValueError names the part and the setting."""
    endpoint = settings.get("endpoint")
    if not isinstance(endpoint, str) or not endpoint.startswith("opc.tcp://"):
        raise ValueError(f'{part}: endpoint: needs "opc.tcp://<plc>:4840/", not {endpoint!r}')
    security = str(settings.get("security", "None")).replace(" ", "")
    certificate, private_key = str(settings.get("certificate", "")), str(settings.get("private_key", ""))
    if security != "None":
        policy, _, mode = security.partition(",")
        if policy not in POLICIES or mode not in MODES:
            raise ValueError(
                f"{part}: security: {security!r} is not None or <policy>,<mode> "
                f"(policies {', '.join(POLICIES)}; modes {', '.join(MODES)})"
            )
        for key, value in (("certificate", certificate), ("private_key", private_key)):
            if not value:
                raise ValueError(f"{part}: {key}: a secure channel needs uacell's client {key.replace('_', ' ')} file")
            if not Path(value).is_file():
                raise ValueError(f"{part}: {key}: no file {value}")
            if Path(value).suffix.lower() not in (".pem", ".der"):
                raise ValueError(f"{part}: {key}: {value} must be a .pem or a .der file (the name says which)")
    username = str(settings.get("username", ""))
    password = ""
    if username:
        file = settings.get("password_file")
        env = str(settings.get("password_env", PASSWORD_ENV))
        try:
            password = read_secret(Path(file) if file else None, env, f"{part}: password_file") or ""
        except SecretError as exc:
            raise ValueError(str(exc)) from None
        if not password:
            raise ValueError(f"{part}: username {username!r}: no password (password_file, or ${env})")
    elif settings.get("password_file"):
        raise ValueError(f"{part}: password_file: needs username")
    mode = str(settings.get("mode", "subscribe"))
    if mode not in ("subscribe", "poll"):
        raise ValueError(f'{part}: mode: "subscribe" or "poll", not {mode!r}')
    default = 0.02 if mode == "subscribe" else 0.1
    interval = settings.get("interval", settings.get("publishing_interval", default))
    if not isinstance(interval, int | float) or isinstance(interval, bool) or not 0.005 <= interval <= 60:
        raise ValueError(f"{part}: interval: seconds between 0.005 and 60, not {interval!r}")
    timeout = settings.get("timeout", LinkOptions.timeout)
    if not isinstance(timeout, int | float) or isinstance(timeout, bool) or not 0.1 <= timeout <= 60:
        raise ValueError(f"{part}: timeout: seconds between 0.1 and 60, not {timeout!r}")
    return LinkOptions(
        endpoint, security, certificate, private_key, username, password, mode, float(interval), float(timeout)
    )


class PlcLink(Listeners):
    def __init__(self, options: LinkOptions) -> None:
        super().__init__()
        self.options = options
        self.endpoint = options.endpoint
        self.timeout = options.timeout
        self.users = 0
        self.log = log
        self._client: Client | None = None
        self._subscription: Any = None
        self._watchdog: asyncio.Task[None] | None = None
        self._last: dict[str, Any] = {}  # poll mode: the value each tag had at the last poll
        # a tag's address (a NodeId string, or a browse path from Objects) -> its NodeId on this connection
        self._resolved: dict[str, ua.NodeId] = {}
        self._address_of: dict[ua.NodeId, str] = {}
        self._task: asyncio.Task[None] | None = None
        self._lost = asyncio.Event()

    # -- what parts use ---------------------------------------------------------------------------

    async def watch(
        self,
        node_ids: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None = None,
        checked: Sequence[str] = (),
    ) -> None:
        """Call ``listener`` with each value of ``node_ids`` (on every connection, then on change);
        ``checked``: only tried, for ``missing``."""
        self._listen(node_ids, listener, on_state, labels, checked)
        if self.connected and self._client is not None:
            try:  # connected already (another part on this PLC): read and subscribe these too
                found = await self._first_read(self._client, [*node_ids, *checked], listener)
                nodes = [node for address, node in found.items() if address in node_ids]
                if self._subscription is not None and nodes:
                    await self._subscription.subscribe_data_change(nodes, queuesize=100, sampling_interval=SAMPLING)
                on_state(True)
            except CommunicationError as exc:
                log.warning("the PLC at %s: %s", self.endpoint, exc)
                self._lost.set()
            except Exception as exc:
                self._lost.set()
                log.warning("the PLC at %s: %s (reconnecting)", self.endpoint, exc)

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"plc {self.endpoint}")

    async def read(self, node_id: str) -> Any:
        client = self._usable()
        try:
            await self._resolve(client, [node_id])
            return await self._node(client, node_id).read_value()
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def read_many(self, node_ids: list[str]) -> list[Any]:
        """Several values in one Read request (the PLC answers them from one scan)."""
        client = self._usable()
        try:
            await self._resolve(client, node_ids)
            values: list[Any] = await client.read_values([self._node(client, n) for n in node_ids])
            return values
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def write(self, node_id: str, value: Any, type_name: str) -> None:
        """Write ``value`` as the built-in type ``type_name`` ("Int32", "Boolean", "Float", ...)."""
        client = self._usable()
        try:
            await self._resolve(client, [node_id])
            await self._node(client, node_id).write_value(ua.DataValue(ua.Variant(value, ua.VariantType[type_name])))
        except ua.UaStatusCodeError as exc:
            raise CommunicationError(f"{self.endpoint}: writing {node_id}: {exc}") from None
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def write_many(self, writes: list[tuple[str, Any, str]]) -> None:
        """Several values in one Write request, in order (the PLC takes them between two scans)."""
        client = self._usable()
        values = [ua.DataValue(ua.Variant(v, ua.VariantType[t])) for _, v, t in writes]
        try:
            await self._resolve(client, [n for n, _, _ in writes])
            nodes = [self._node(client, n) for n, _, _ in writes]
            await client.write_values(nodes, values)
        except ua.UaStatusCodeError as exc:
            raise CommunicationError(f"{self.endpoint}: writing {[n for n, _, _ in writes]}: {exc}") from None
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def close(self) -> None:
        await stop_task(self._task)
        await self._disconnect()

    # -- the connection ---------------------------------------------------------------------------

    def _usable(self) -> Client:
        if not self.connected or self._client is None:
            raise CommunicationError(f"no connection to the PLC at {self.endpoint}")
        return self._client

    def _failed(self, exc: BaseException) -> CommunicationError:
        self._lost.set()
        return CommunicationError(f"{self.endpoint}: {exc or type(exc).__name__}")

    async def _run(self) -> None:
        await keep_trying(self._session)

    async def _session(self) -> bool:
        """Connect and serve the parts until the connection is lost; True if it was up."""
        up = False
        try:
            await self._connect()
            up = True
            await self._lost.wait()
            self._report_lost()
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self._report_failed(str(exc) or type(exc).__name__, server_lost(exc))
        self._set_connected(False)
        await self._disconnect()
        return up

    async def _connect(self) -> None:
        self._lost.clear()
        o = self.options
        self._client = client = await new_client(o, self.timeout)
        await client.connect()
        self._resolved.clear()
        self._address_of.clear()
        self.missing.clear()
        # a first read of everything (a missing tag is set aside in ``missing``, the parts say so)
        found = await self._first_read(client, self.tried(), None)
        nodes = [node for address, node in found.items() if address in self._watched]
        if o.mode == "poll":
            self._announce()
            self._watchdog = asyncio.get_running_loop().create_task(self._poll(client))
            return
        link = self

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                link._deliver(link._address_of.get(node.nodeid, node.nodeid.to_string()), val)

            def status_change_notification(self, status: Any) -> None:
                link._lost.set()

        subscription = await client.create_subscription(o.interval * 1000, Handler())
        if nodes:
            await subscription.subscribe_data_change(nodes, queuesize=100, sampling_interval=SAMPLING)
        self._subscription = subscription
        self._announce()
        self._watchdog = asyncio.get_running_loop().create_task(self._keepalive(client))

    async def _first_read(self, client: Client, addresses: list[str], listener: ValueListener | None) -> dict[str, Any]:
        """Read each address once and deliver its value (to ``listener``, else to every part watching
        it); an address the PLC has no node for, or answers with a bad status, goes to ``missing``.
        The nodes of the others are returned by address (to subscribe)."""
        nodes = {}
        for nid in addresses:
            try:
                await self._resolve(client, [nid])
            except CommunicationError as exc:
                self.missing[nid] = str(exc).rpartition(": ")[2]
                continue
            node = self._node(client, nid)
            dv = await node.read_data_value(raise_on_bad_status=False)
            if not dv.StatusCode.is_good():
                self.missing[nid] = dv.StatusCode.name
                continue
            value = dv.Value.Value if dv.Value is not None else None
            self._last[nid] = value
            if listener is not None:
                listener(nid, value)
            else:
                self._deliver(nid, value)
            nodes[nid] = node
        return nodes

    async def _poll(self, client: Client) -> None:
        """Poll mode: every watched tag in one Read request each ``interval``; changes delivered."""
        interval = self.options.interval
        while not self._lost.is_set():
            await asyncio.sleep(interval)
            ids = self.present()
            try:
                values = await client.read_values([self._node(client, n) for n in ids])
            except Exception as exc:
                log.info("the PLC at %s: a poll failed (%s)", self.endpoint, exc or type(exc).__name__)
                self._lost.set()
                return
            for nid, value in zip(ids, values, strict=True):
                if nid not in self._last or self._last[nid] != value:
                    self._last[nid] = value
                    self._deliver(nid, value)

    async def _keepalive(self, client: Client) -> None:
        """A PLC that stops answering is noticed only when a request fails: ask every second, and
        call it lost when it has not answered within the link's ``timeout``."""
        while not self._lost.is_set():
            await asyncio.sleep(1.0)
            try:
                state = client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()
                await asyncio.wait_for(state, self.timeout)
            except Exception:
                self._lost.set()

    async def _resolve(self, client: Client, addresses: list[str]) -> None:
        """Find the NodeIds of the addresses that are browse paths (one TranslateBrowsePaths request
        each; a path the PLC does not have is named)."""
        for address in addresses:
            if address in self._resolved:
                continue
            try:
                nodeid = await resolve_address(client, address, self.endpoint)
            except CommunicationError as exc:
                raise CommunicationError(str(exc).replace(address, self.named(address), 1)) from None
            self._resolved[address] = nodeid
            self._address_of[nodeid] = address

    def _node(self, client: Client, address: str) -> Any:
        nodeid = self._resolved.get(address)
        if nodeid is None:
            if address.startswith("/"):
                raise KeyError(address)
            nodeid = ua.NodeId.from_string(address)
        return client.get_node(nodeid)

    async def _disconnect(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
        self._subscription = None
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), 2.0)


async def new_client(o: LinkOptions, timeout: float) -> Client:
    """An asyncua client for the PLC, its channel security and user set (not yet connected)."""
    quiet_client()
    # asyncua's own health probe (every ``watchdog_intervall``, which is also how long it waits for
    # the answer; 1 s by default) would drop a PLC that pauses for just over a second, on a loaded
    # host too: it gets the link's ``timeout``, the same tolerance as ``PlcLink._keepalive``.
    client = Client(o.endpoint, timeout=timeout, watchdog_intervall=timeout)
    client.session_timeout = 30_000
    if o.security != "None":
        client.application_uri = _application_uri(o.certificate) or client.application_uri
        await client.set_security_string(f"{o.security},{o.certificate},{o.private_key}")
    if o.username:
        client.set_user(o.username)
        client.set_password(o.password)
    return client


async def resolve_address(client: Client, address: str, endpoint: str = "") -> ua.NodeId:
    """A tag's NodeId: ``address`` is a NodeId string (``ns=3;s=Capper.PackTags.Status.StateCurrent``)
    or a browse path from the Objects folder (``/3:Capper/3:PackTags/3:Status/3:StateCurrent``)."""
    if not address.startswith("/"):
        return ua.NodeId.from_string(address)
    segments = [p for p in address.split("/") if p]
    try:
        node = await client.nodes.objects.get_child(segments)
    except ua.UaStatusCodeError as exc:
        raise CommunicationError(f"{endpoint}: {address}: {ua.StatusCode(exc.code).name}") from None
    nodeid: ua.NodeId = node.nodeid
    return nodeid


def _application_uri(certificate: str) -> str | None:
    """The URI in a certificate's subjectAltName: the ApplicationUri a client using it must send."""
    from cryptography import x509

    data = Path(certificate).read_bytes()
    try:
        cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else x509.load_der_x509_certificate(data)
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except (ValueError, x509.ExtensionNotFound):
        return None
    uris = names.get_values_for_type(x509.UniformResourceIdentifier)
    return uris[0] if uris else None


def link_pool() -> SharedPool[LinkOptions, PlcLink]:
    """Links shared per endpoint and options: fifty units on one PLC use one connection."""
    return SharedPool(lambda link: link.close(), lambda link: link.endpoint)


def shared_link(pool: SharedPool[LinkOptions, PlcLink], options: LinkOptions, part: str = "") -> PlcLink:
    return pool.get(options, lambda: PlcLink(options), part)
