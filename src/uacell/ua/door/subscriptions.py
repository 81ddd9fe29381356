"""What uacell reads and sets of asyncua's client subscriptions to keep them to their sessions (decision 80):
the retransmission queue, the publishing loop at a new interval, a subscription moved to another
session's connection, and the current values sent again.

asyncua keeps one table of subscriptions for the whole server and answers every session's request for
any of them; ``uacell.ua.subscriptions`` checks whose a subscription is before it comes here.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from asyncua import ua
from asyncua.server.internal_subscription import InternalSubscription

log = logging.getLogger(__name__)


def retransmission_queue(sub: InternalSubscription) -> dict[int, ua.PublishResult]:
    """The messages sent and not yet acknowledged, by sequence number (oldest first)."""
    queue: dict[int, ua.PublishResult] = sub._not_acknowledged_results
    return queue


def restart_loop(sub: InternalSubscription) -> None:
    """Run the subscription's publishing loop again at its (revised) ``RevisedPublishingInterval``:
    asyncua's loop reads its period once, when it starts."""
    task = sub._task
    if task is None:
        return  # stopped, or never looping (a server-side subscription of 0 ms)
    task.cancel()
    sub._task = asyncio.create_task(sub._subscription_loop())


async def move(sub: InternalSubscription, session_id: ua.NodeId, processor: Any) -> None:
    """``sub`` now belongs to ``session_id``, its messages to ``processor``'s connection. The connection
    it leaves is sent a StatusChangeNotification Good_SubscriptionTransferred (OPC 10000-4 5.14.7) if it
    has a Publish request waiting, and is no longer called back for it. asyncua moved the answers only:
    the old connection's Publish requests still carried the new session's notifications."""
    old = getattr(sub.pub_request_callback, "__self__", None)
    sub.session_id = session_id
    sub.pub_result_callback = processor.forward_publish_response
    sub.pub_request_callback = processor.get_publish_request
    if old is None or old is processor:
        return
    sid = sub.data.SubscriptionId
    old._publish_results_subs.pop(sid, None)
    if not old._publish_requests:
        return
    requestdata = old._publish_requests.popleft()
    result = ua.PublishResult(SubscriptionId=sid)
    result.NotificationMessage.SequenceNumber = sub._notification_seq  # not kept for retransmission
    status = ua.StatusChangeNotification(Status=ua.StatusCode(ua.StatusCodes.GoodSubscriptionTransferred))
    result.NotificationMessage.NotificationData.append(status)
    try:
        await old.forward_publish_response(result, requestdata)
    except Exception:  # the old connection may be closing: the transfer stands
        log.info("could not tell the old session that subscription %s was transferred", sid, exc_info=True)


async def send_current_values(sub: InternalSubscription) -> None:
    """Each Reporting data item queues its current value, whether it changed or not (TransferSubscriptions'
    SendInitialValues)."""
    service = sub.monitored_item_srv
    for mdata in list(service._monitored_items.values()):
        rvid = mdata.read_value_id
        if mdata.mode != ua.MonitoringMode.Reporting or mdata.callback_handle is None or rvid is None:
            continue
        mdata.mvalue.current_dvalue = None  # reported again even when it equals the last one
        await service.trigger_datachange(mdata.callback_handle, rvid.NodeId, rvid.AttributeId)
