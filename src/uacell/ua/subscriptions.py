"""A subscription belongs to the session that created it (OPC 10000-4 5.14, decision 80).

asyncua keeps one table of subscriptions for the whole server and served any session's request for any
of them: a second client could delete another's subscription, switch its publishing off, add, change or
delete its monitored items, acknowledge its messages or read them with Republish, or take it over with
TransferSubscriptions whoever its user was. Subscription ids are small consecutive numbers, so guessing
one takes nothing. Here every subscription service a session asks for looks only at the session's own
subscriptions; another session's answers Bad_SubscriptionIdInvalid, as an unknown one does, so that
nobody learns which ids exist.

Besides:

- Publish: Bad_NoSubscription when the session has no subscription (asyncua queued the request while
  any session had one); an acknowledgement of an unknown message is Bad_SequenceNumberUnknown.
- Republish: Bad_MessageNotAvailable for a message not in the retransmission queue (asyncua answered
  Good with an empty message), and the message stays queued until acknowledged (asyncua removed it).
- ModifySubscription: revises and applies the publishing interval, the counts and
  MaxNotificationsPerPublish (asyncua changed nothing and answered the values of the creation).
- TransferSubscriptions: by OPC 10000-4 5.14.7 only to a session of the same user, or between anonymous
  sessions of the same ApplicationUri over signed channels (Bad_UserAccessDenied otherwise);
  Bad_NothingToDo for a subscription the session already owns; the old session is sent
  Good_SubscriptionTransferred; SendInitialValues honoured.

``OwnSubscriptions`` is a mixin of uacell's session (``uacell.ua.limits.LimitedSession``); what it reads
and sets of asyncua's subscriptions is in ``uacell.ua.door.subscriptions``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from asyncua.common.utils import ServiceError

from uacell.ua import context, door
from uacell.ua.door import connection, enums, monitoring, publishing
from uacell.ua.door import subscriptions as door_subscriptions

log = logging.getLogger(__name__)

#: The fastest publishing interval the server supports, in ms (node-opcua's server's figure): a request
#: below it (0, negative, NaN) is revised to it, OPC 10000-4 5.14.2.2 (decision 79).
FASTEST_PUBLISHING_INTERVAL = 50.0
#: The slowest, in ms (an hour): a request above it (infinity included) is revised to it.
SLOWEST_PUBLISHING_INTERVAL = 3_600_000.0

_SIGNED = (ua.MessageSecurityMode.Sign, ua.MessageSecurityMode.SignAndEncrypt)


def revised_interval(requested: float) -> tuple[float, bool]:
    """The publishing interval for a requested one, and whether its changes go out at once (a request
    below the fastest interval, decision 79)."""
    if math.isnan(requested) or requested < FASTEST_PUBLISHING_INTERVAL:
        return FASTEST_PUBLISHING_INTERVAL, True
    return min(requested, SLOWEST_PUBLISHING_INTERVAL), False


def revised_counts(lifetime: int, keep_alive: int, max_lifetime: int, max_keep_alive: int) -> tuple[int, int]:
    """The lifetime and keep-alive counts for requested ones: 0 is the server's maximum, a count above
    it the maximum, and the lifetime at least three keep-alives (OPC 10000-4 5.14.2.2)."""
    keep_alive = min(keep_alive, max_keep_alive) if keep_alive > 0 else max_keep_alive
    lifetime = min(lifetime, max_lifetime) if lifetime > 0 else max_lifetime
    return max(lifetime, 3 * keep_alive), keep_alive


@dataclass(frozen=True)
class Identity:
    """Who a session acts for, as TransferSubscriptions compares it: the user (None for anonymous), the
    client's ApplicationUri and its channel's security mode."""

    user: str | None
    application_uri: str
    mode: ua.MessageSecurityMode

    def may_take_from(self, owner: Identity) -> bool:
        """May a session of this identity take over a subscription of ``owner``'s (OPC 10000-4 5.14.7)?"""
        if self.user is not None or owner.user is not None:
            return self.user == owner.user
        return (
            bool(self.application_uri)
            and self.application_uri == owner.application_uri
            and self.mode in _SIGNED
            and owner.mode in _SIGNED
        )


def identity(session: Any) -> Identity:
    """A session's identity now (its user may change with a later ActivateSession): the caller's user and
    client ApplicationUri as everything else sees them (``context.caller_of``), its channel's mode."""
    caller = context.caller_of(session)
    return Identity(caller.user, caller.client, door.tagged(session, "channel_mode", ua.MessageSecurityMode.None_))


def owned_by_caller(sid: Any) -> bool:
    """Is ``sid`` a subscription of the session whose request is under way (ConditionRefresh's argument)?
    True outside a client's request (the server's own calls)."""
    session = getattr(context.current_processor(), "session", None)
    if not isinstance(session, OwnSubscriptions):
        return True
    return isinstance(sid, int) and session.mine(sid) is not None


def _status(code: int) -> ua.StatusCode:
    return ua.StatusCode(code)


class OwnSubscriptions:
    """The subscription services of one session, each over the session's own subscriptions only."""

    # what the mixin finds on asyncua's InternalSession
    session_id: ua.NodeId
    subscription_service: Any
    iserver: Any

    def note_channel(self) -> None:
        """Keep the security mode of the channel the session is created on (for TransferSubscriptions)."""
        _policy, mode = connection.channel_policy(context.current_processor())
        door.tag(self, "channel_mode", mode)

    def _own_subscriptions(self) -> list[Any]:
        subs = self.subscription_service.subscriptions.values()
        return [s for s in subs if s.session_id == self.session_id]

    def mine(self, sid: int) -> Any:
        """The session's subscription ``sid``, or None (unknown, or another session's)."""
        sub = self.subscription_service.subscriptions.get(sid)
        return sub if sub is not None and sub.session_id == self.session_id else None

    def _subscription(self, sid: int) -> Any:
        """The session's subscription ``sid``; Bad_SubscriptionIdInvalid for any other."""
        sub = self.mine(sid)
        if sub is None:
            raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
        return sub

    def revise_counts(self, lifetime: int, keep_alive: int) -> tuple[int, int]:
        return revised_counts(lifetime, keep_alive, self.iserver.max_lifetime_count, self.iserver.max_keep_alive_count)

    # --- services --------------------------------------------------------------------------------------
    async def modify_monitored_items(self, params: ua.ModifyMonitoredItemsParameters) -> Any:
        self._subscription(params.SubscriptionId)
        return await super().modify_monitored_items(params)  # type: ignore[misc]

    async def delete_monitored_items(self, params: ua.DeleteMonitoredItemsParameters) -> Any:
        sub = self._subscription(params.SubscriptionId)
        results = await super().delete_monitored_items(params)  # type: ignore[misc]
        monitoring.forget(sub, list(params.MonitoredItemIds or ()))
        return results

    async def set_monitoring_mode(self, params: ua.SetMonitoringModeParameters) -> Any:
        self._subscription(params.SubscriptionId)
        if not enums.known(params.MonitoringMode, ua.MonitoringMode):
            raise ServiceError(ua.StatusCodes.BadMonitoringModeInvalid)
        return await super().set_monitoring_mode(params)  # type: ignore[misc]

    async def set_triggering(self, params: ua.SetTriggeringParameters) -> ua.SetTriggeringResult:
        """SetTriggering (OPC 10000-4 5.13.5; asyncua has none): ``uacell.ua.door.monitoring`` keeps the links."""
        return monitoring.set_triggering(self._subscription(params.SubscriptionId), params)

    async def delete_subscriptions(self, ids: list[int]) -> list[ua.StatusCode]:
        mine = [sid for sid in ids if self.mine(sid) is not None]
        done = iter(await super().delete_subscriptions(mine) if mine else ())  # type: ignore[misc]
        return [next(done) if sid in mine else _status(ua.StatusCodes.BadSubscriptionIdInvalid) for sid in ids]

    async def set_publishing_mode(self, params: ua.SetPublishingModeParameters) -> list[ua.StatusCode]:
        results: list[ua.StatusCode] = []
        for sid in params.SubscriptionIds:
            sub = self.mine(sid)
            if sub is None:
                results.append(_status(ua.StatusCodes.BadSubscriptionIdInvalid))
            else:
                await sub.set_publishing_mode(params.PublishingEnabled)
                results.append(_status(ua.StatusCodes.Good))
        return results

    def publish(self, acks: list[ua.SubscriptionAcknowledgement] | None = None) -> tuple[int, list[ua.StatusCode]]:
        own = self._own_subscriptions()
        if not own:
            raise ServiceError(ua.StatusCodes.BadNoSubscription)
        results: list[ua.StatusCode] = []
        for ack in acks or ():
            sub = self.mine(ack.SubscriptionId)
            if sub is None:
                results.append(_status(ua.StatusCodes.BadSubscriptionIdInvalid))
            elif door_subscriptions.retransmission_queue(sub).pop(ack.SequenceNumber, None) is None:
                results.append(_status(ua.StatusCodes.BadSequenceNumberUnknown))
            else:
                results.append(_status(ua.StatusCodes.Good))
        return len(own), results

    def republish(self, params: ua.RepublishParameters) -> ua.NotificationMessage:
        sub = self._subscription(params.SubscriptionId)
        kept = door_subscriptions.retransmission_queue(sub).get(params.RetransmitSequenceNumber)
        if kept is None:
            raise ServiceError(ua.StatusCodes.BadMessageNotAvailable)
        message: ua.NotificationMessage = kept.NotificationMessage
        return message

    def modify_subscription(self, params: ua.ModifySubscriptionParameters) -> ua.ModifySubscriptionResult:
        sub = self._subscription(params.SubscriptionId)
        interval, at_once = revised_interval(params.RequestedPublishingInterval)
        lifetime, keep_alive = self.revise_counts(params.RequestedLifetimeCount, params.RequestedMaxKeepAliveCount)
        data = sub.data
        moved = interval != data.RevisedPublishingInterval
        data.RevisedPublishingInterval = interval
        data.RevisedLifetimeCount, data.RevisedMaxKeepAliveCount = lifetime, keep_alive
        publishing.limit_notifications(sub, params.MaxNotificationsPerPublish)
        if moved:  # the same interval again (asyncua's client sends back the revised one): kept as it was
            publishing.publish_at_once(sub, at_once)
            door_subscriptions.restart_loop(sub)
        log.info("subscription %s modified: %.0f ms, lifetime %d, keep-alive %d", sub, interval, lifetime, keep_alive)
        return ua.ModifySubscriptionResult(
            RevisedPublishingInterval=interval, RevisedLifetimeCount=lifetime, RevisedMaxKeepAliveCount=keep_alive
        )

    async def transfer_subscriptions(
        self, params: ua.TransferSubscriptionsParameters, callback: Any
    ) -> list[ua.TransferResult]:
        processor = callback.__self__  # the connection the transfer request came on (asyncua passes its method)
        me = identity(self)
        sessions = {s.session_id: s for s in connection.external_sessions(self.iserver)}
        room = self.room_for_subscriptions()
        results: list[ua.TransferResult] = []
        for sid in params.SubscriptionIds:
            sub = self.subscription_service.subscriptions.get(int(sid))
            owner = sessions.get(sub.session_id) if sub is not None else None
            owner_identity = identity(owner) if owner is not None else door.tagged(sub, "owner", None)
            if sub is None:
                code = ua.StatusCodes.BadSubscriptionIdInvalid
            elif sub.session_id == self.session_id:
                code = ua.StatusCodes.BadNothingToDo
            elif owner_identity is None or not me.may_take_from(owner_identity):
                code = ua.StatusCodes.BadUserAccessDenied
            elif room <= 0:
                code = ua.StatusCodes.BadTooManySubscriptions
            else:
                await door_subscriptions.move(sub, self.session_id, processor)
                door.tag(sub, "owner", me)
                room -= 1
                if params.SendInitialValues:
                    await door_subscriptions.send_current_values(sub)
                queued = sorted(door_subscriptions.retransmission_queue(sub))
                results.append(ua.TransferResult(AvailableSequenceNumbers=queued))
                log.info("subscription %s transferred to session %s", sid, self.session_id)
                continue
            results.append(ua.TransferResult(StatusCode=_status(code)))
        return results

    def room_for_subscriptions(self) -> int:
        """How many more subscriptions this session may have (uacell's session counts them against its
        limits)."""
        return 1 << 31
