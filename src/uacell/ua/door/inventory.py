# ruff: noqa: E501  (one entry a line: the inventory reads as a table)
"""Everything uacell changes in asyncua (and uvicorn, and the one stdlib module it speeds up), and the
private names it reads: one entry each. ``uacell.ua.door`` refuses to install anything not listed
here; ``tests/test_asyncua_door.py`` checks the list against what a started server installed and
against the installed asyncua (every private name still there). docs/asyncua.md shows it as a table.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

# The versions every entry was read against (docs/asyncua.md: how to upgrade).
VERIFIED = {"asyncua": "2.1.0", "uvicorn": "0.54.0"}


class Kind(StrEnum):
    PATCH = "class attribute replaced"  # process-wide, at attach
    SWAP = "instance attribute replaced"  # on one server's object
    SETTING = "public attribute set"  # a setting asyncua reads from an attribute (no setter)
    SUBCLASS = "subclass"
    PRIVATE = "private name read"  # read (or written back) through a door function


@dataclass(frozen=True)
class Entry:
    target: str  # dotted path: module, class, attribute
    kind: Kind
    owner: str  # the uacell module that asks for it
    why: str
    replaces: str  # asyncua's behaviour it replaces ("" for a private read)
    at_start: bool = True  # installed by every started server (else only on some paths)

    @property
    def package(self) -> str:
        return self.target.split(".")[0]


_P = "asyncua.server.uaprocessor.UaProcessor"
_T = "asyncua.server.binary_server_asyncio.OPCUAProtocol"
_S = "asyncua.server.internal_session.InternalSession"
_I = "asyncua.server.internal_server.InternalServer"

ENTRIES: tuple[Entry, ...] = (
    # --- the request path (door/processing.py, asked for by ua/pipeline.py) ------------------------
    Entry(f"{_P}._process_message", Kind.PATCH, "uacell.ua.pipeline", "the request stages; Call, Read, HistoryUpdate, BrowseNext, RegisterNodes, Cancel by one lookup; calls apart (decisions 48, 51)", "its service dispatch by comparing the request type with 40 NodeIds"),
    Entry(f"{_P}.process_message", Kind.PATCH, "uacell.ua.pipeline", "request header decoded by ua/codec.py; faults answered in one place (decision 50)", "struct_from_binary of the header; its error handling"),
    Entry(f"{_P}.process", Kind.PATCH, "uacell.ua.pipeline", "the channel guard before an OpenSecureChannel; a refusal closes the connection in one INFO line", "logs a traceback at ERROR and keeps the connection"),
    Entry(f"{_P}.open_secure_channel", Kind.PATCH, "uacell.ua.pipeline", "only the policies and modes the endpoints offer (security/policy.py)", "select_policy keeps its default (None) channel when a client asks for it, offered or not"),
    Entry(f"{_T}.data_received", Kind.PATCH, "uacell.ua.pipeline", "chunk sizes checked before buffering (ua/limits.py); a parsed message runs at once", "buffers any declared size; wakes the connection's task per message"),
    Entry(f"{_T}._process_one_msg", Kind.PATCH, "uacell.ua.pipeline", "one message at a time when the first ran at once (decision 51)", "its message loop's step"),
    Entry(f"{_T}.connection_made", Kind.PATCH, "uacell.ua.pipeline", "admission: room made, handshake deadline (ua/limits.py)", "refuses beyond max_connections only"),
    Entry(f"{_S}.call", Kind.PATCH, "uacell.ua.pipeline", "the session known while its calls run (ua/context.py)", "(wrapped, not changed)"),
    Entry(f"{_S}.read", Kind.PATCH, "uacell.ua.pipeline", "read hooks: role-dependent values (security/policy.py)", "(wrapped, not changed)"),
    Entry(f"{_S}.history_read", Kind.PATCH, "uacell.ua.pipeline", "the session known while history is read", "(wrapped, not changed)"),
    Entry(f"{_P}.send_response", Kind.PATCH, "uacell.ua.pipeline", "no answer once the connection is gone: a client that went while its request ran (decision 105)", "writes on the closed transport: under uvloop the write raises, and the request is logged at ERROR as failed"),
    Entry(f"{_P}.get_publish_request", Kind.PATCH, "uacell.ua.pipeline", "no Publish request on a closed connection: a subscription whose session outlives its connection keeps its notifications for the session's next channel (decision 105; door/publishing.py)", "answers a request the lost connection left waiting on the closed transport: under uvloop the write raises, and the subscription's loop logs a traceback at ERROR and ends for good"),
    Entry("asyncua.server.internal_subscription.InternalSubscription._trigger_publish", Kind.PATCH, "uacell.ua.pipeline", "a client's subscription asked for below the fastest interval (0 included; revised to it, decision 79) publishes once per event-loop turn, every change of the turn in one NotificationMessage (door/publishing.py)", "publishes at the first queued change of each monitored item"),
    Entry("asyncua.server.internal_subscription.InternalSubscription._pop_publish_result", Kind.PATCH, "uacell.ua.pipeline", "at most the client's MaxNotificationsPerPublish notifications in one message, MoreNotifications set while more are queued (door/publishing.py)", "every queued notification in one message, whatever the client asked"),
    Entry("asyncua.server.internal_subscription.InternalSubscription.publish_results", Kind.PATCH, "uacell.ua.pipeline", "the rest of a limited message goes with the next Publish request", "(wrapped, not changed)"),
    Entry("asyncua.server.internal_subscription.InternalSubscription._enqueue_event", Kind.PATCH, "uacell.ua.pipeline", "an item in Sampling mode queues and does not report until it reports or an item linked to it by SetTriggering reports; a Disabled event item queues nothing (OPC 10000-4 7.23, 5.13.5; door/monitoring.py)", "queues and reports an item's notifications whatever its mode (events even when Disabled)"),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService.datachange_callback", Kind.PATCH, "uacell.ua.pipeline", "a value reported by OPC 10000-4 7.22.2: compared with the last value reported, a status change always (ua/datachange.py); the part an IndexRange names, the timestamps TimestampsToReturn names (decision 81); sampled at the item's interval, the latest value at the next sample (decision 86); a scalar kept as written (door/monitoring.py)", "compares with the value before (a slow drift within the deadband never reported; a status change within it dropped); the whole value whatever the IndexRange, both timestamps; every change however close together; a deepcopy of every value for every monitored item"),
    Entry("asyncua.ua.uaprotocol_auto.BrowseDirection._missing_", Kind.PATCH, "uacell.ua.pipeline", "a BrowseDirection out of range is Bad_BrowseDirectionInvalid for its BrowseDescription (OPC 10000-4 5.8.2); decoded as a stand-in the service refuses with its own code (door/enums.py)", "an unknown number failed the whole request's decoding: Bad_DecodingError"),
    Entry("asyncua.ua.uaprotocol_auto.TimestampsToReturn._missing_", Kind.PATCH, "uacell.ua.pipeline", "a TimestampsToReturn out of range is Bad_TimestampsToReturnInvalid (Read, HistoryRead per node, Create/ModifyMonitoredItems); decoded as a stand-in the service refuses with its own code (door/enums.py)", "an unknown number failed the whole request's decoding: Bad_DecodingError"),
    Entry("asyncua.ua.uaprotocol_auto.MonitoringMode._missing_", Kind.PATCH, "uacell.ua.pipeline", "a MonitoringMode out of range is Bad_MonitoringModeInvalid (per item of CreateMonitoredItems; SetMonitoringMode); decoded as a stand-in the service refuses with its own code (door/enums.py)", "an unknown number failed the whole request's decoding: Bad_DecodingError"),
    Entry("asyncua.ua.uaprotocol_auto.DataChangeTrigger._missing_", Kind.PATCH, "uacell.ua.pipeline", "a DataChangeFilter's Trigger out of range is Bad_MonitoredItemFilterInvalid for its item; decoded as a stand-in the service refuses with its own code (door/enums.py)", "an unknown number failed the whole request's decoding: Bad_DecodingError"),
    Entry("asyncua.ua.uaprotocol_auto.FilterOperator._missing_", Kind.PATCH, "uacell.ua.pipeline", "a FilterOperator out of range is Bad_FilterOperatorInvalid for its element (Bad_MonitoredItemFilterInvalid for the item); decoded as a stand-in the service refuses with its own code (door/enums.py)", "an unknown number failed the whole request's decoding: Bad_DecodingError"),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService.create_monitored_items", Kind.PATCH, "uacell.ua.pipeline", "a filter the standards do not allow refused with their status code, the request's other items made (ua/datachange.py); a data item's queue of 0 or 1 is 1 (decision 83); the sampling interval revised by 7.21 (decision 86); an event item's EventFilterResult (decision 87)", "accepts any filter: a deadband on a String, a DataChangeFilter on an event item (the whole request failed), a percent deadband it did not apply; a data item's queue of 0 made its largest; the publishing interval as every item's sampling interval; no FilterResult"),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService.modify_monitored_items", Kind.PATCH, "uacell.ua.pipeline", "the same checks for a new filter; an unknown item is Bad_MonitoredItemIdInvalid; the queue size and sampling interval revised as at creation (decisions 83, 86)", "accepts any filter; an unknown item failed the whole request (a TypeError); any queue size, uncapped; the requested sampling interval echoed, -1 included"),
    Entry("asyncua.server.monitored_item_service.MonitoredItemData.where_clause_evaluator", Kind.SWAP, "uacell.ua.pipeline", "an event item's WhereClause evaluated by ua/content_filter.py: OfType true for subtypes, Like and Between evaluated, an operator it cannot evaluate refused when the item is made (decision 82)", "OfType compared the event type exactly (a filter on BaseEventType or ConditionType passed nothing); Like raised and dropped every event; an unsupported operator accepted and every event dropped", at_start=False),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService.set_monitoring_mode", Kind.PATCH, "uacell.ua.pipeline", "an item enabled again reports its first sample (OPC 10000-4 5.13.1.3)", "reports it only when the value changed while the item was disabled"),
    Entry(f"{_T}.messages", Kind.SWAP, "uacell.ua.pipeline", "collects what asyncua parses from one read, to run it at once", "its queue, for the duration of one parse"),
    # --- one server's parts ------------------------------------------------------------------------
    Entry(f"{_I}.method_service", Kind.SWAP, "uacell.binding.dispatch", "the one method dispatcher", "MethodService: calls the callback with no argument checks or roles"),
    Entry(f"{_I}.time_task", Kind.SWAP, "uacell.server", "a stop cancels asyncua's clock (ServerStatus.CurrentTime written once a second) and takes its task away first", "InternalServer.stop waits for the clock's next wake-up: up to a second a stop", at_start=False),
    Entry(f"{_I}.history_manager", Kind.SWAP, "uacell.history.service", "uacell's history (stores, retention, events, HistoryUpdate)", "HistoryManager with its in-memory storage"),
    Entry("asyncua.server.subscription_service.SubscriptionService.trigger_event", Kind.SWAP, "uacell.ua.event_tap", "every fired event to history and PubSub first", "(wrapped, not changed)"),
    Entry(f"{_I}.create_session", Kind.SWAP, "uacell.security.policy", "uacell's session class (limits, audit, roles)", "creates an InternalSession"),
    Entry(f"{_I}.decrypt_user_token", Kind.SWAP, "uacell.security.policy", "password decryption with the policy's rules, off the loop", "its decryption"),
    Entry("asyncua.server.server.Server._setup_server_nodes", Kind.SWAP, "uacell.security.policy", "a server certificate a CA issued is sent with the CA's certificates (door/certificate.py, decision 95)", "the endpoints and the channels' policies with the server's certificate alone", at_start=False),
    Entry("asyncua.crypto.security_policies.SecurityPolicyFactory.create", Kind.SWAP, "uacell.security.policy", "each channel's policy holds the server's certificate followed by its CA's (OPN's SenderCertificate, CreateSession's serverCertificate; decision 95)", "the server's certificate alone", at_start=False),
    Entry("asyncua.crypto.security_policies.Cryptography.verify", Kind.SWAP, "uacell.security.policy", "ActivateSession's clientSignature checked over the leaf certificate first, then the whole chain (OPC 10000-4 5.7.3.2; decision 95)", "checked over the certificate the policy holds only", at_start=False),
    Entry("asyncua.crypto.security_policies.SecurityPolicyFactory.certificate", Kind.SETTING, "uacell.security.push", "ApplyChanges: new channels use the certificate UpdateCertificate installed (decision 96)", "", at_start=False),
    Entry("asyncua.crypto.security_policies.SecurityPolicyFactory.private_key", Kind.SETTING, "uacell.security.push", "ApplyChanges: new channels use the key of that certificate (decision 96)", "", at_start=False),
    Entry("asyncua.server.server.Server._policies", Kind.PRIVATE, "uacell.security.policy", "the channels' policy factories, given the server's chain (decision 95)", ""),
    Entry(f"{_I}.verify_x509_token", Kind.SWAP, "uacell.security.policy", "user certificates checked by OPC 10000-4 and bound to users (decision 84)", "its signature check, which took any algorithm"),
    Entry(f"{_I}.load_standard_address_space", Kind.SWAP, "uacell.ua.nodesets", "the standard nodes from the address-space snapshot (decision 46)", "loads the standard nodes from asyncua's generated code", at_start=False),
    Entry("asyncua.server.address_space.ViewService._suitable_reftype", Kind.SWAP, "uacell.ua.nodesets", "the reference-type subtype closure cached while an import adds inverse references", "walks the type tree per reference", at_start=False),
    Entry("asyncua.server.address_space.AddressSpace._nodes", Kind.PRIVATE, "uacell.ua.nodesets", "the node table, copied to and restored from the snapshot", ""),
    # --- settings asyncua reads from attributes ------------------------------------------------------
    Entry(f"{_I}.certificate", Kind.SETTING, "uacell.security.policy", "the server certificate (asyncua's setter reads a file path)", ""),
    Entry(f"{_I}.private_key", Kind.SETTING, "uacell.security.policy", "the server key, decrypted by uacell", ""),
    Entry(f"{_I}.max_connections", Kind.SETTING, "uacell.ua.limits", "[limits] connections", ""),
    Entry(f"{_I}.max_subscriptions", Kind.SETTING, "uacell.ua.limits", "[limits] subscriptions", ""),
    Entry(f"{_I}.max_pending_activation_seconds", Kind.SETTING, "uacell.ua.limits", "[limits] activation_timeout", ""),
    Entry(f"{_I}.max_pending_messages_per_connection", Kind.SETTING, "uacell.ua.limits", "[limits] pending chunks", ""),
    Entry("asyncua.server.server.Server.limits", Kind.SETTING, "uacell.ua.limits", "transport limits per connection (ServerTransportLimits)", "TransportLimits"),
    Entry(f"{_I}.bind_condition_methods", Kind.SETTING, "uacell.server", "ConditionType's methods bound by asyncua in batches", ""),
    Entry("asyncua.server.server.Server.product_uri", Kind.SETTING, "uacell.server", "the server's ProductUri", ""),
    # --- subclasses ----------------------------------------------------------------------------------
    Entry("asyncua.server.address_space.MethodService", Kind.SUBCLASS, "uacell.binding.dispatch", "MethodDispatcher: the one method dispatcher (argument checks, roles, guards, serialization)", "MethodService.call"),
    Entry(_S, Kind.SUBCLASS, "uacell.ua.limits", "LimitedSession: sessions, subscriptions, monitored items, operations per request counted; every subscription service over the session's own subscriptions, ModifySubscription applied, Republish and TransferSubscriptions by OPC 10000-4 (ua/subscriptions.py, decision 80); Browse with continuation points, BrowseNext, TranslateBrowsePathsToNodeIds, Read's IndexRange and Write's checks by OPC 10000-4 5.9 and 5.11 (ua/views.py, ua/attributes.py, decision 81)", "unlimited sessions; any session's request served for any subscription of the server; RequestedMaxReferencesPerNode and IndexRange ignored, no BrowseNext"),
    Entry("asyncua.common.connection.TransportLimits", Kind.SUBCLASS, "uacell.ua.limits", "ServerTransportLimits: chunk sizes from the Hello, message size enforced", "create_acknowledge_and_set_limits"),
    Entry("asyncua.common.xmlimporter.XmlImporter", Kind.SUBCLASS, "uacell.ua.nodesets", "the subtype closure cached while inverse references are added (start-up time)", "_add_missing_reverse_references", at_start=False),
    Entry("asyncua.crypto.permission_rules.User", Kind.SUBCLASS, "uacell.ua.context", "UacellUser: the user with uacell's role", "User"),
    Entry("uvicorn.protocols.http.h11_impl.H11Protocol", Kind.SUBCLASS, "uacell.web.guards", "TimedHeaders: a request's headers within a deadline (slow-header clients)", "no header deadline", at_start=False),
    # --- the standard library ------------------------------------------------------------------------
    Entry("dataclasses.exec", Kind.PATCH, "uacell.ua.codecache", "asyncua's 900 dataclasses built from cached code objects (start-up time)", "dataclasses compiles each class's methods", at_start=False),
    # --- private names read ----------------------------------------------------------------------------
    Entry(f"{_P}._connection", Kind.PRIVATE, "uacell.ua.channel", "a channel's policy, mode, peer certificate, open state", ""),
    Entry(f"{_P}._transport", Kind.PRIVATE, "uacell.ua.channel", "to send an Error or a response, to close; whether the connection is gone (decision 105)", ""),
    Entry(f"{_P}._limits", Kind.PRIVATE, "uacell.ua.limits", "the negotiated receive buffer", ""),
    Entry("asyncua.common.connection.SecureConnection._sequence_number", Kind.PRIVATE, "uacell.ua.pipeline", "a one-chunk response on SecurityPolicy None framed from its fixed layout (the channel's sequence number read and advanced as asyncua does)", ""),
    Entry("asyncua.common.connection.SecureConnection._limits", Kind.PRIVATE, "uacell.ua.pipeline", "the negotiated send buffer: does a response fit one chunk", ""),
    Entry("asyncua.common.connection.SecureConnection._incoming_parts", Kind.PRIVATE, "uacell.ua.pipeline", "a one-chunk request on SecurityPolicy None read from its fixed layout only when no longer message is under way", ""),
    Entry("asyncua.common.connection.SecureConnection._peer_sequence_number", Kind.PRIVATE, "uacell.ua.pipeline", "the client's sequence number checked and advanced as asyncua does", ""),
    Entry("asyncua.common.utils.Buffer._cur_pos", Kind.PRIVATE, "uacell.ua.pipeline", "where a received chunk's body starts", ""),
    Entry(f"{_T}._buffer", Kind.PRIVATE, "uacell.ua.limits", "bytes received and not parsed (chunk sizes checked first)", ""),
    Entry("asyncio.Queue._queue", Kind.PRIVATE, "uacell.ua.limits", "bytes queued on a connection (asyncua's message queue)", ""),
    Entry(f"{_I}._external_sessions", Kind.PRIVATE, "uacell.ua.channel", "the client sessions (diagnostics, metrics)", ""),
    Entry(f"{_S}._last_activity", Kind.PRIVATE, "uacell.services.diagnostics", "a session's idle time", ""),
    Entry("asyncua.common.utils.Buffer._data", Kind.PRIVATE, "uacell.ua.codec", "a request's bytes, decoded by ua/codec.py", ""),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService._monitored_items", Kind.PRIVATE, "uacell.ua.limits", "monitored items counted against [limits]; an item's filter and last value reported (door/monitoring.py)", ""),
    Entry("asyncua.server.monitored_item_service.MonitoredItemService._monitored_datachange", Kind.PRIVATE, "uacell.ua.pipeline", "the monitored item a data change callback's handle belongs to (door/monitoring.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._triggered_datachanges", Kind.PRIVATE, "uacell.ua.pipeline", "the queued data changes, held back beyond MaxNotificationsPerPublish (door/publishing.py); a Sampling item's, queued when it reports (door/monitoring.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._triggered_events", Kind.PRIVATE, "uacell.ua.pipeline", "the queued events, held back beyond MaxNotificationsPerPublish (door/publishing.py); a Sampling item's, queued when it reports (door/monitoring.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._publishing_enabled", Kind.PRIVATE, "uacell.ua.pipeline", "whether a publish takes the queued notifications (door/publishing.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._not_acknowledged_results", Kind.PRIVATE, "uacell.ua.limits", "the retransmission queue: acknowledged, republished and listed by a session's own requests only (door/subscriptions.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._task", Kind.PRIVATE, "uacell.ua.limits", "the publishing loop, run again at a modified interval (door/subscriptions.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._subscription_loop", Kind.PRIVATE, "uacell.ua.limits", "the publishing loop, run again at a modified interval (door/subscriptions.py)", ""),
    Entry("asyncua.server.internal_subscription.InternalSubscription._notification_seq", Kind.PRIVATE, "uacell.ua.limits", "the sequence number of the Good_SubscriptionTransferred message to the old session (door/subscriptions.py)", ""),
    Entry(f"{_P}._publish_requests", Kind.PRIVATE, "uacell.ua.limits", "a Publish request the old session of a transferred subscription has waiting, for its Good_SubscriptionTransferred (door/subscriptions.py); those of a closed connection, dropped (door/publishing.py)", ""),
    Entry(f"{_P}._publish_results_subs", Kind.PRIVATE, "uacell.ua.limits", "a transferred subscription is no longer published with the old session's Publish requests (door/subscriptions.py)", ""),
    Entry("asyncua.server.address_space.MethodService._call", Kind.PRIVATE, "uacell.binding.dispatch", "asyncua's callback for a method uacell does not bind (ConditionRefresh)", ""),
    Entry("asyncua.server.address_space.ViewService._get_sub_ref", Kind.PRIVATE, "uacell.ua.nodesets", "the subtypes of a reference type", ""),
)  # fmt: skip

INVENTORY: dict[str, Entry] = {e.target: e for e in ENTRIES}
