"""One JetStream ordered consumer on the replicas' no_drop stream, narrowed to subjects.

Both readers of the stream use it: a session's feed
(:class:`~fleetctl.server.cluster.sessionfeed.SessionFeed`) and a replica's reader of the
other replicas' no_drop frames (:class:`~fleetctl.server.cluster.remotefeed.RemoteFeed`).
An ordered consumer delivers in stream order and, when its NATS node goes (two idle
heartbeats missed) or a gap shows, nats-py re-creates it after the last message it
delivered.
"""

from __future__ import annotations

import datetime
from collections.abc import Awaitable, Callable

from nats.aio.msg import Msg
from nats.js import JetStreamContext, api

# JetStream's idle heartbeat for an ordered consumer: two missed ones (a NATS node gone)
# make the client re-create the consumer after the last sequence it got.
IDLE_HEARTBEAT_S = 1.0


async def subscribe_ordered(js: JetStreamContext, stream: str, subjects: tuple[str, ...],
                            cb: Callable[[Msg], Awaitable[None]], *,
                            start_seq: int | None = None, start_time: float | None = None,
                            pending_msgs: int, pending_bytes: int,
                            ) -> JetStreamContext.PushSubscription:
    """An ordered consumer on *subjects* of *stream* (one or more; JetStream's
    ``filter_subjects`` for several), from stream sequence *start_seq*, else from wall
    time *start_time* (seconds), else from the next message stored.

    Raises:
        nats.errors.Error: NATS or JetStream refused (callers log and retry).
    """
    if start_seq is not None:
        config = api.ConsumerConfig(deliver_policy=api.DeliverPolicy.BY_START_SEQUENCE,
                                    opt_start_seq=start_seq)
    elif start_time is not None:
        config = api.ConsumerConfig(
            deliver_policy=api.DeliverPolicy.BY_START_TIME,
            opt_start_time=datetime.datetime.fromtimestamp(start_time, datetime.UTC))
    else:
        config = api.ConsumerConfig(deliver_policy=api.DeliverPolicy.NEW)
    if len(subjects) > 1:
        config.filter_subjects = list(subjects)
    sub = await js.subscribe(subjects[0], stream=stream, cb=cb, ordered_consumer=True,
                             config=config, idle_heartbeat=IDLE_HEARTBEAT_S,
                             pending_msgs_limit=pending_msgs,
                             pending_bytes_limit=pending_bytes)
    # nats-py re-creates an ordered consumer (after a gap, or missed heartbeats when a
    # NATS node goes) from this same config object, switched to "by start sequence";
    # JetStream refuses that while a start time is still set (err 10094). Before the first
    # message that sequence may be 1: a reader started by time keeps its own floor.
    config.opt_start_time = None
    return sub
