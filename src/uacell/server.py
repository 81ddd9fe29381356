"""Assemble one asyncua Server from a configuration: models, cell, bindings, endpoints."""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from asyncua import Server, ua

from uacell import __version__
from uacell.binding.cell import CellBuilder, Part, build_cell, cell_digest
from uacell.binding.dispatch import MethodDispatcher
from uacell.binding.machine_binding import NodeRefs
from uacell.binding.publisher import Publisher
from uacell.binding.space import Space
from uacell.binding.writes import WriteRouter
from uacell.catalog import companions as catalog_companions
from uacell.config import Config, default_application_uri
from uacell.core.background import stop_task
from uacell.core.companion import Binder, Closer, Companion, datasets_of, models_of, shape_function, shapes_digest
from uacell.core.file_store import HandlePool
from uacell.core.forked import ForkFailed, forking, run_forked
from uacell.core.logs import configured_levels
from uacell.core.registry import Registries, Registry, RegistryKey, T
from uacell.core.rights import RoleTable
from uacell.core.roles import Role, listening_policy, may
from uacell.history.service import HistoryService
from uacell.history.setup import add_configurations, history_shape, install_history
from uacell.host import ServerView
from uacell.models import StateTables, official_models
from uacell.security.access import UacellUserManager
from uacell.security.audit import AuditTrail
from uacell.security.pki import PkiPaths
from uacell.security.policy import SecurityStage, install_security
from uacell.security.push import ServerConfiguration
from uacell.security.users import UserStore
from uacell.services.diagnostics import Diagnostics, bind_subscription_methods
from uacell.services.discovery_registration import DiscoveryRegistration, Registrant, discovery_url
from uacell.services.observers import install_audit
from uacell.services.shutdown import announce_shutdown, no_shutdown_yet
from uacell.ua import door
from uacell.ua.door.certificate import served_certificate
from uacell.ua.event_tap import EventTap
from uacell.ua.limits import DecodingStage, admit, guard_bytes, install_limits, publish_operation_limits
from uacell.ua.nodesets import WRITE_SHARE, SnapshotJob, init_address_space
from uacell.ua.pipeline import ContextStage, Pipeline, PublishedStage
from uacell.ua.snapshot import Cancel, WriteCancelled, prune

if TYPE_CHECKING:  # imported when [metrics] or [pubsub] is on (prometheus-client, aiomqtt)
    from uacell.pubsub.service import PubSubService
    from uacell.services.metrics import Metrics
    from uacell.sparkplug.service import SparkplugService

log = logging.getLogger(__name__)

APPLICATION_URI = default_application_uri()  # unless [server] application_uri says otherwise
PRODUCT_URI = "urn:uacell"

__all__ = ["Binder", "UacellServer", "default_binders"]


def _quiet_asyncua() -> None:
    # asyncua logs every NodeSet quirk and every session at INFO/WARNING; keep uacell's log readable.
    # A level set in [logging] levels wins.
    for name in ("asyncua", "asyncua.common.xmlimporter", "asyncua.server.address_space"):
        logger = logging.getLogger(name)
        if name not in configured_levels:
            logger.setLevel(logging.ERROR)


class UacellServer:
    """One uacell server: call ``setup()``, then ``start()``; ``stop()`` at the end.

    This is the application object binders receive. What they bind they register in typed registries
    keyed by the part's browse path (``app.registry(CONTROLLERS)["Robot1.Controllers.Controller1"]``);
    the keys are declared next to the parts' code.
    """

    def __init__(
        self,
        config: Config,
        binders: list[Binder[ServerView]] | None = None,
        parts: list[tuple[str, Part]] | None = None,
        companions: Sequence[Companion[ServerView]] | None = None,
    ) -> None:
        _quiet_asyncua()
        self.config = config
        # The companions this server serves (default: this build's, ``uacell.catalog``): handed from
        # here to the parts that read their declarations (history, PubSub, Sparkplug, metrics).
        self.companions = tuple(companions) if companions is not None else catalog_companions()
        self.datasets = datasets_of(self.companions)
        self.parts = parts  # the cell's parts; None: the demo cell
        self.server = Server()
        self._cell: CellBuilder | None = None
        self.model_indexes: dict[str, int] = {}
        # The state-machine tables of the configured NodeSets: binders hand them to the models.
        # The official NodeSet files of the companions served, in load order.
        self.models = official_models(models_of(self.companions))
        self.tables = StateTables(self.models, config.server.models_dir)
        self.binders = binders if binders is not None else default_binders(self.companions)
        self._closers: list[Closer] = []
        self.registries = Registries()
        self.dispatcher = MethodDispatcher.install(self.server, RoleTable(self.companions))
        self.publisher = Publisher()
        self.dispatcher.after_call.append(self.publisher.schedule)
        self.publisher.idle_hooks.append(self.dispatcher.refresh_touched)
        self.publisher.touch_hooks.append(self.dispatcher.touch)
        self._refs: NodeRefs | None = None
        self.writes = WriteRouter()
        self.space = Space(self.server)  # what binders may do to the address space (uacell.host.BinderHost)
        limits = config.limits
        # Every file handle any client holds, over all FileType trees (docs/security.md, "Limits").
        self.file_handles = HandlePool(limits.file_handles_per_session, limits.file_handles)
        self.audit = AuditTrail(None)  # the configured trail from setup() on
        self.metrics: Metrics | None = None
        self.diagnostics: Diagnostics | None = None
        self.address_space_source = ""  # "snapshot" or "nodesets", once set up
        self.snapshot_digest = ""
        self._snapshot_job: SnapshotJob | None = None
        self._snapshot_cancel = threading.Event()
        self._snapshot_task: asyncio.Task[None] | None = None
        self.discovery_registration: DiscoveryRegistration | None = None  # with [discovery] url
        self._listening = False  # from start() until a stop begins
        self.history: HistoryService | None = None  # HistoryRead ([history], docs/history.md)
        self.pubsub: PubSubService | None = None  # PubSub JSON over MQTT ([pubsub], docs/pubsub.md)
        self.sparkplug: SparkplugService | None = None  # Sparkplug B ([sparkplug], docs/sparkplug.md)
        self.event_tap = EventTap(self.server.iserver)  # every event fired, for history and PubSub

    @property
    def cell(self) -> CellBuilder:
        """The built cell (binders run after it is built)."""
        if self._cell is None:
            raise RuntimeError("the cell is built in setup()")
        return self._cell

    @property
    def refs(self) -> NodeRefs:
        if self._refs is None:
            raise RuntimeError("the namespaces are known in setup()")
        return self._refs

    def registry(self, key: RegistryKey[T]) -> Registry[T]:
        """The registry ``key`` names (created empty on first use)."""
        return self.registries.of(key)

    @property
    def data_dir(self) -> Path:
        return self.config.server.data_dir

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.config.server.host}:{self.config.server.port}/"

    def served_certificate(self) -> bytes:
        """The server certificate (DER) new secure channels get: the file's until a GDS's ApplyChanges."""
        return served_certificate(self.server)

    async def setup(self) -> None:
        _quiet_asyncua()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.audit = AuditTrail.for_config(self.config)
        install_audit(self, self.audit)
        cfg = self.config.server
        anonymous = Role.parse(cfg.anonymous_role) if cfg.anonymous_role else None
        self.policy = listening_policy([cfg.host], anonymous, cfg.allow_none_security)
        for warning in self.policy.warnings:
            log.warning("%s", warning)
        self.users = UserStore.in_data_dir(self.data_dir)
        self.server.iserver.set_user_manager(UacellUserManager(self.policy, self.users))
        # ConditionRefresh(2) for alarm clients, with Severity 100 on its RefreshStart/End events.
        door.configure(self.server.iserver, "InternalServer.bind_condition_methods", 100)
        # asyncua's init(), the official models and the cell's instances: from the address-space
        # snapshot when there is one for this cell, else built (and a snapshot written once listening).
        parts = self.parts if self.parts is not None else self.config.cell.parts()
        # what the snapshot of the address space is keyed by, beside the models and the code
        shapes = [c.shape for c in self.companions if c.shape is not None]
        shaped = f"{history_shape(self.config.history)},shapes={shapes_digest(shapes)}"
        roots = [root for c in self.companions for root in c.roots]
        self.snapshot_digest = digest = cell_digest(parts, shaped, roots=roots)
        prepared = await init_address_space(self.server, self.models, cfg.models_dir, cfg.snapshot_dir, digest)
        self.model_indexes = prepared.indexes
        self.address_space_source = prepared.source
        if prepared.extras is not None:  # the state-machine tables an earlier start read from the NodeSets
            self.tables.adopt(prepared.extras.get("fsm_tables"))
        self._cell = await build_cell(
            self.server, self.model_indexes, parts, restored=prepared.extras, type_index=prepared.types, roots=roots
        )
        if prepared.capture is not None:
            # the nodes of uacell's own the companions give their parts, and the HA Configuration
            # nodes of kept variables, are part of the cell's shape: in the snapshot
            for spec in shapes:
                await shape_function(spec)(self.space, self._cell)
            kept = [(b.part.role, b.node) for b in self._cell.built]
            await add_configurations(self.server, self.config.history, kept, self.datasets)
            self._snapshot_job = await prepared.capture()
        self.limits = install_limits(self)
        self.server.set_endpoint(self.endpoint)
        self.server.set_server_name(cfg.application_name)
        await self.server.set_application_uri(cfg.application_uri)
        # State machines fire AuditUpdateStateEvents for the transitions calls cause (binding/machine_binding.py).
        await self.server.get_node(ua.ObjectIds.Server_Auditing).write_value(True)
        self.security = await install_security(self)
        self._closers.append(self.security.watch_users())  # sessions follow users.toml (decision 99)
        self._closers.append(self.security.watch_trust())  # channels follow the trust list (decision 100)
        self.diagnostics = Diagnostics(self)
        # What every request passes, outermost first (ua/pipeline.py says what each stage does).
        self.pipeline = Pipeline(
            [
                PublishedStage(self.publisher),
                ContextStage(),
                self.diagnostics,
                SecurityStage(self.security),
                DecodingStage(),
            ],
            admission=admit,
            bytes_guard=guard_bytes,
            channel_guard=self.security,
            refused=self.security.message_refused,
        )
        self.pipeline.install(self.server.iserver)
        door.configure(self.server, "Server.product_uri", PRODUCT_URI)
        await self.server.set_build_info(PRODUCT_URI, "uacell", "uacell", __version__, "0", ua.DateTime.now())
        self._refs = NodeRefs(await self.server.get_namespace_array())
        self.dispatcher.declarations = self.cell.instantiator.declarations
        bind_subscription_methods(self)
        self.server_configuration = ServerConfiguration(self)
        await self.server_configuration.bind()
        for binder in self.binders:
            closer = await binder(self)
            if closer is not None:
                self._closers.append(closer)
        self.event_tap.install()
        kept = [(b.part.role, b.node) for b in self.cell.built]
        self.history = await install_history(
            self.server,
            self.config.history,
            self.data_dir,
            kept,
            lambda role: may(Role.parse(role), "history_read"),
            self.event_tap,
            self.datasets,
        )
        if self.history is not None:  # a closed session's released continuation points are forgotten
            self.security.on_session_closed.append(self.history.forget_session)
        if self.config.pubsub.enabled:
            from uacell.pubsub.service import PartRef, install_pubsub

            aspace = self.server.iserver.aspace
            namespace_array = ua.NodeId(ua.ObjectIds.Server_NamespaceArray)
            self.pubsub = await install_pubsub(
                self.config.pubsub,
                aspace,
                self.cell.instantiator,
                lambda: aspace.read_attribute_value(namespace_array, ua.AttributeIds.Value).Value.Value or [],
                [PartRef(b.part.role, b.node, b.path) for b in self.cell.built],
                self.config.server.port,
                self.data_dir,
                datasets=self.datasets,
            )
        if self.config.sparkplug.enabled:
            self.sparkplug = self._sparkplug()

    def _sparkplug(self) -> SparkplugService | None:
        from uacell.pubsub.service import default_publisher_id
        from uacell.sparkplug.devices import PartRef as SparkplugPart
        from uacell.sparkplug.service import install_sparkplug

        return install_sparkplug(
            self.config.sparkplug,
            self.server.iserver.aspace,
            self.dispatcher,
            [SparkplugPart(b.part.role, b.node, b.path) for b in self.cell.built],
            default_publisher_id(self.config.server.port),
            self.data_dir,
            self.datasets,
        )

    async def start(self) -> None:
        await publish_operation_limits(self.server, self.limits)
        await self.server.start()
        await no_shutdown_yet(self.server)
        self._listening = True
        if self._snapshot_job is not None:  # first start: write the snapshot for the next ones
            # The cell's bookkeeping as the binders left it (types they looked up included).
            extras = {**self.cell.extras(), "fsm_tables": self.tables.made()}
            write = functools.partial(self._snapshot_job, extras)
            self._snapshot_task = asyncio.get_running_loop().create_task(self._write_snapshot(write))
            self._snapshot_job = None
        await self.dispatcher.refresh_executable()
        if self.pubsub is not None:
            self.pubsub.start(self.event_tap)
        if self.sparkplug is not None:
            self.sparkplug.start()
        if self.diagnostics is not None:
            await self.diagnostics.start()
        if self.config.metrics.enabled:
            from uacell.services.metrics import Metrics

            self.metrics = Metrics(self, self.companions)
            if self.pubsub is not None:
                from uacell.pubsub.metrics import PubSubCollector

                self.metrics.registry.register(PubSubCollector(self.pubsub.link))
            if self.sparkplug is not None:
                from uacell.sparkplug.metrics import SparkplugCollector

                self.metrics.registry.register(SparkplugCollector(self.sparkplug))
            await self.metrics.start(self.config.metrics.host, self.config.metrics.port)
        if self.config.discovery.url:
            cfg, pki = self.config.server, PkiPaths.in_data_dir(self.data_dir)
            registrant = Registrant(
                server_uri=cfg.application_uri,  # the URI the certificate carries
                product_uri=PRODUCT_URI,
                name=cfg.application_name,
                discovery_urls=[discovery_url(cfg.host, cfg.port)],
                capabilities=self.config.discovery.capabilities,
                certificate=pki.cert,
                private_key=pki.key,
            )
            self.discovery_registration = DiscoveryRegistration(self.config.discovery, registrant)
            self.discovery_registration.start()

    async def _write_snapshot(self, job: Callable[[Cancel, float], tuple[Path, int]]) -> None:
        """Written beside the serving event loop: by a forked child where the platform has fork, so
        that the loop keeps the interpreter (``uacell.core.forked``), else (or when the fork fails) by
        a thread taking ``WRITE_SHARE`` of it."""
        cancel = self._snapshot_cancel
        written: tuple[Path, int] | None = None
        try:
            if forking() and self.config.server.snapshot_fork:
                try:
                    written = await run_forked(lambda cancelled: job(cancelled, 1.0), cancel)
                except ForkFailed as e:
                    log.info("the address-space snapshot is written by a thread (%s)", e.strerror)
            if written is None:
                written = await asyncio.to_thread(job, cancel, WRITE_SHARE)
        except WriteCancelled:
            log.info("the address-space snapshot was not written: the server stopped first")
        except Exception as e:  # a cache: the server runs on without it
            log.warning("could not write the address-space snapshot: %s", e)
        else:
            prune(written[0].parent)
            log.info("wrote the address-space snapshot %s (%d nodes)", *written)

    async def snapshot_written(self) -> None:
        """Wait until the snapshot this start writes (if any) is on disk, or given up."""
        if self._snapshot_task is not None:
            await asyncio.shield(self._snapshot_task)

    async def settle(self) -> None:
        """Wait until every model change so far is visible in the address space."""
        await self.publisher.flush()
        await self.dispatcher.refresh_executable()

    async def announce_stop(self) -> float:
        """Tell connected clients the server stops and give them ``[server] shutdown_delay`` to leave
        (decision 85); the seconds it waited. Once per start: ``stop`` calls it when nobody did."""
        if not self._listening:
            return 0.0
        self._listening = False
        return await announce_shutdown(self.server, self.config.server.shutdown_delay, self.security.on_session_closed)

    async def stop(self) -> None:
        await self.announce_stop()
        if self.discovery_registration is not None:  # unregistered while still answering
            await self.discovery_registration.stop()
        # New calls answer Bad_Shutdown; those under way finish before the equipment goes away.
        await self.dispatcher.close()
        for closer in reversed(self._closers):
            try:
                await closer()
            except Exception:
                log.exception("error while shutting down")
        await self.publisher.close()
        if self.pubsub is not None:  # the last values out, then the status Disabled
            await self.pubsub.stop()
        if self.sparkplug is not None:  # the last values out, then the NDEATH
            await self.sparkplug.stop()
        if self.diagnostics is not None:
            await self.diagnostics.stop()
        # asyncua's stop would wait for its clock (CurrentTime, once a second) to wake: up to a second
        await stop_task(door.swap(self.server.iserver, "InternalServer.time_task", None))
        await self.server.stop()
        self._snapshot_cancel.set()  # a stop is never held up by a cache
        await self.snapshot_written()
        if self.metrics is not None:
            await self.metrics.stop()
        self.audit.close()


def default_binders(companions: Sequence[Companion[ServerView]] | None = None) -> list[Binder[ServerView]]:
    """The binders of ``companions`` (default: this build's, ``uacell.catalog``), in their order."""
    found = companions if companions is not None else catalog_companions()
    return [c.binder for c in found if c.binder is not None]


if TYPE_CHECKING:  # the server is the host its parts and binders are typed against
    from uacell.host import BinderHost

    def _is_a_host(app: UacellServer) -> BinderHost:
        return app
