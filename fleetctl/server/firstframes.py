"""What makes a topic show at once for a new subscriber, wired to the relay core.

- Latched messages (:mod:`fleetctl.server.latched`): a latched frame the relay accepted is
  kept; a new subscription gets the stored messages of the topics it starts receiving,
  ahead of live data (:meth:`OutboundScheduler.push_latched`), with the same receive check
  as live data. An auth reload forgets what a sender may no longer send.
- Keyframe requests (:mod:`fleetctl.server.keyframes`): ``/keyframe_requests`` frames are
  checked (the asker may receive the topic) and forwarded to the video topic's publisher;
  a new subscription to a known video topic makes the server ask its publisher itself.

What a new subscription costs is bounded: the stores are indexed
(:class:`~fleetctl.server.topicindex.TopicIndex`), so a prefix pattern or a literal topic
is matched only against the stored topics it may match, and a pattern that must look at
every stored topic is charged to the connection's control request rate in proportion to
the work (:data:`WORK_PER_CONTROL_REQUEST`).

Functions over a :class:`~fleetctl.server.relay.RelayCore`, like :mod:`.reauth`, so the
relay's hot path stays in one short module.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING

from fleetctl.server.authmap import Identity
from fleetctl.server.latched import SenderKey
from fleetctl.server.permissions import Permissions
from fleetctl.wire.control import (
    KEYFRAME_REQUEST_TYPE,
    KEYFRAME_REQUESTS_TOPIC,
    decode_keyframe_request,
    encode_keyframe_request,
)
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FragmentHeader, read_fragment_header

if TYPE_CHECKING:
    from fleetctl.server.peer import Peer
    from fleetctl.server.relay import RelayCore

log = logging.getLogger("fleetctl.server")

# Why: the refusal memo is keyed by asker-chosen topics; keep it small per connection.
_MAX_REFUSED_MEMO = 256
# Video topics of other replicas' publishers remembered (the oldest is forgotten).
MAX_REMOTE_VIDEO_TOPICS = 4096
# Work (about one regex call, 2-4 us of the event loop, see Matched) a new subscription
# may cost within its one control request; each further such amount costs one more. Why:
# a pattern no index can narrow (".*") is matched against every stored topic, 4,096 per
# store: 14.7 ms with a full latched store, and a token churning such patterns at the
# control rate (20/s) cost the loop 0.3-0.6 s a second. Charged, one identity set's
# churn costs the loop at most ~256 units per control request, ~20 ms a second.
WORK_PER_CONTROL_REQUEST = 256
# Event loop time a new subscription's first frames may take within its one control
# request; each further such amount costs one more (the charge is the larger of the two).
# Why both: units count calls, not what a call costs, and one can cost 100 times more (a
# connection's 200 ".*/xN" patterns joined run as an NFA in RE2's memory budget: 85 us a
# call); 1 ms is about what 256 units take here.
LOOP_S_PER_CONTROL_REQUEST = 0.001


def sender_key(peer: Peer) -> SenderKey:
    """Who a latched message is kept for: the sender's identity names, sorted."""
    return tuple(sorted(peer.identity_names))


def keep_latched(core: RelayCore, peer: Peer, topic: str, frame: bytes, root: int,
                 is_fragment: bool) -> None:
    """Hand a latched frame *peer* was allowed to send (already relayed) to the store.

    A fragment whose header does not read is not kept (counted as ``malformed``; its
    receivers drop it too).
    """
    fragment: FragmentHeader | None = None
    if is_fragment:
        try:
            fragment = read_fragment_header(frame, root)
        except WireError:
            events = core.metrics.latched_events
            events["malformed"] = events.get("malformed", 0) + 1
            return
    core.latched.put(sender_key(peer), topic, frame, fragment)


def on_new_subscriptions(core: RelayCore, peer: Peer, patterns: Sequence[str]) -> int:
    """*peer* just added *patterns* (one, or a resumed session's): queue the stored
    latched messages of the topics it starts receiving through them, and ask the
    publishers of its new video topics for a keyframe.

    Only the stored topics the patterns may match are looked at (:class:`TopicIndex`): a
    prefix pattern or a literal topic costs what it finds. A pattern RE2 cannot bound
    (``.*``, ``.*scan``) is matched against every stored topic, up to 4,096 per store;
    a session's patterns are matched together, each store looked at once (200 such
    patterns resumed one by one took 1.1 s beside a full latched store).

    Returns:
        The work it took (:class:`Matched`): see :func:`extra_requests`.
    """
    work = _queue_latched(core, peer, patterns) + _ask_for_keyframes(core, peer, patterns)
    if core.remote_video:  # replicas: publishers elsewhere route it (rate limit there)
        work += _ask_replicas_for_keyframes(core, peer, patterns)
    return work


def extra_requests(work: int, elapsed_s: float) -> int:
    """Control requests new subscriptions cost beyond their own, which the relay charges
    to the connection's control request rate: one per :data:`WORK_PER_CONTROL_REQUEST`
    units of *work* or per :data:`LOOP_S_PER_CONTROL_REQUEST` of *elapsed_s* (the loop
    time their first frames took), whichever is more."""
    return max(work // WORK_PER_CONTROL_REQUEST, int(elapsed_s / LOOP_S_PER_CONTROL_REQUEST))


def _queue_latched(core: RelayCore, peer: Peer, patterns: Sequence[str]) -> int:
    """Queue the stored latched messages *patterns* newly deliver to *peer*; the work."""
    store = core.latched
    if not len(store):
        return 0
    found = core.subs.newly_matched(peer, patterns, store.candidates)
    for topic in found.topics:
        for frames in store.messages(topic):
            if peer.outbound.push_latched(topic, frames):
                core.metrics.latched_delivered += len(frames)
    return found.work


def _ask_for_keyframes(core: RelayCore, peer: Peer, patterns: Sequence[str]) -> int:
    """Ask the publishers of the video topics *patterns* newly deliver to *peer* for a
    keyframe (once per topic per interval); the work."""
    router = core.keyframes
    found = core.subs.newly_matched(peer, patterns, router.candidates)
    for topic in found.topics:
        publisher = router.publisher(topic)
        if publisher is None or publisher is peer:
            continue
        if router.route(topic) is not None:
            publisher.outbound.push(KEYFRAME_REQUESTS_TOPIC, router.request_frame(topic), True)
            core.metrics.count_keyframe_request("auto")
    return found.work


def _ask_replicas_for_keyframes(core: RelayCore, peer: Peer, patterns: Sequence[str]) -> int:
    """The same for video topics published on other replicas; the work."""
    found = core.subs.newly_matched(peer, patterns, core.remote_video.candidates)
    for topic in found.topics:
        if core.keyframes.publisher(topic) is None and core.fanout.forward_keyframe_request(
                encode_keyframe_request(topic)):
            core.metrics.count_keyframe_request("auto_to_replicas")
    return found.work


def on_remote_video_topic(core: RelayCore, topic: str) -> None:
    """The first video frame of *topic* from another replica: its publisher is there.
    Remember the topic, and ask for a keyframe now: this replica receives the topic
    because a local viewer just subscribed (interest follows subscriptions), and that
    viewer cannot decode before a keyframe."""
    if len(core.remote_video) >= MAX_REMOTE_VIDEO_TOPICS:
        core.remote_video.discard(core.remote_video.oldest())
    core.remote_video.add(topic)
    if core.fanout.forward_keyframe_request(encode_keyframe_request(topic)):
        core.metrics.count_keyframe_request("auto_to_replicas")


def on_keyframe_request(core: RelayCore, peer: Peer, frame: bytes, type_name: str) -> None:
    """A frame on ``/keyframe_requests``: forward it to the video topic's publisher if
    *peer* may receive that topic (no send rule is needed: it is a control topic)."""
    assert peer.perms is not None
    if type_name != KEYFRAME_REQUEST_TYPE:
        core.metrics.count_keyframe_request("malformed")
        core.malformed(peer, "unknown_type", KEYFRAME_REQUESTS_TOPIC,
                       f"{KEYFRAME_REQUESTS_TOPIC} carries KeyframeRequest, not {type_name}")
        return
    try:
        topic = decode_keyframe_request(frame)
    except WireError as exc:
        core.metrics.count_keyframe_request("malformed")
        core.malformed(peer, "malformed_frame", KEYFRAME_REQUESTS_TOPIC, str(exc))
        return
    core.metrics.count_in(KEYFRAME_REQUESTS_TOPIC, len(frame))
    if not peer.perms.may_receive(topic):
        core.metrics.count_keyframe_request("refused")
        _refuse_once(core, peer, topic)
        return
    if core.keyframes.publisher(topic) is None and core.fanout.forward_keyframe_request(frame):
        # Replicas: the publisher may be on another one, which routes it (rate limit
        # included) if it is there.
        core.metrics.count_keyframe_request("to_replicas")
        return
    _route_keyframe_request(core, topic, frame)


def on_remote_keyframe_request(core: RelayCore, frame: bytes) -> None:
    """Another replica's viewer asked for a keyframe (already checked there): forward it
    if the video topic's publisher is connected here.

    Raises:
        WireError: The frame is not a KeyframeRequest.
    """
    topic = decode_keyframe_request(frame)
    if core.keyframes.publisher(topic) is not None:
        _route_keyframe_request(core, topic, frame)


def _route_keyframe_request(core: RelayCore, topic: str, frame: bytes) -> None:
    publisher = core.keyframes.route(topic)
    if publisher is not None:
        publisher.outbound.push(KEYFRAME_REQUESTS_TOPIC, frame, True)
        core.metrics.count_keyframe_request("forwarded")


def _refuse_once(core: RelayCore, peer: Peer, topic: str) -> None:
    # A page asks again on every undecodable frame: answer once per topic per connection.
    memo = peer.refused_keyframes
    if topic in memo or len(memo) >= _MAX_REFUSED_MEMO:
        core.metrics.count_error("keyframe_refused")
        return
    memo.add(topic)
    log.warning("%s may not ask for keyframes of %r", peer.label, topic)
    core.send_error(peer, "keyframe_refused", topic[:200],
                    f"no receive permission on {topic[:200]!r}: keyframe request not sent")


def sender_may_send(core: RelayCore, sender: SenderKey, topic: str) -> bool:
    """Whether the identities *sender* names all exist in the current auth map and may
    together send on *topic* (a latched message kept for them may be served)."""
    perms = _sender_permissions(core, {i.name: i for i in core.auth.identities}, sender)
    return perms is not None and perms.may_send(topic)


def _sender_permissions(core: RelayCore, by_name: dict[str, Identity],
                        sender: SenderKey) -> Permissions | None:
    """The permissions of *sender*'s identities, or ``None`` when one is gone from the
    auth map (*by_name*: its identities by name)."""
    found = [by_name[n] for n in sender if n in by_name]
    return core.pool.get(found) if len(found) == len(sender) else None


def drop_revoked_latched(core: RelayCore) -> int:
    """After an auth reload: forget latched messages whose sender's identities are gone
    from the map, or whose identities may no longer send on the topic.

    Returns:
        Entries dropped.
    """
    by_name = {i.name: i for i in core.auth.identities}
    perms: dict[SenderKey, Permissions | None] = {}

    def revoked(sender: SenderKey, topic: str) -> bool:
        if sender not in perms:  # one Permissions per sender, not per entry
            perms[sender] = _sender_permissions(core, by_name, sender)
        allowed = perms[sender]
        return allowed is None or not allowed.may_send(topic)

    dropped = core.latched.drop_where(revoked)
    if dropped:
        log.info("auth map reloaded: %d latched messages of revoked senders forgotten",
                 dropped)
    return dropped
