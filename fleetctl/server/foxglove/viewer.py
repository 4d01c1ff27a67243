"""One Foxglove connection: its channels, subscriptions and client channels, turned into
relay core calls. No I/O: answers go into the connection's outbound scheduler, which the
adapter's writer drains (:mod:`fleetctl.server.foxglove.adapter`).

Mapping (docs/foxglove.md):

- a server channel is a ``(topic, type)`` of the :class:`TopicCatalog` the viewer's
  receive rules allow; a Foxglove subscription is a core subscription to the exact topic
  (an escaped RE2 pattern), so the core's ACL, latched messages and per-connection
  latest-per-topic queue apply as to any fleetctl consumer;
- a client channel (``clientPublish``) is a topic the send rules allow; each Client Message
  Data (CDR) becomes one fleetctl frame handed to :meth:`RelayCore.on_binary`, which checks
  the send rules again and routes it like a robot's frame;
- the core's error frames become Status messages (level error); its other control frames
  (welcome, subscription acks) mean nothing to Foxglove and are not sent.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from typing import Any

from fleetctl.server.foxglove import messages as fx
from fleetctl.server.foxglove.catalog import TopicCatalog
from fleetctl.server.foxglove.transcode import Converted
from fleetctl.server.peer import Peer
from fleetctl.server.permissions import Permissions
from fleetctl.server.relay import RelayCore
from fleetctl.wire.codec import Codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import normalize_type

# Why: Foxglove subscribes per channel; a viewer holds at most this many at once.
MAX_CLIENT_CHANNELS = 256


class Viewer:
    """The Foxglove state of one connection.

    Args:
        core: The relay core.
        peer: The connection's core state (authenticated before :meth:`start`).
        catalog: The server's channels.
        codec: Encodes client messages as fleetctl frames.
        session_id: Server Info ``sessionId`` (one per server run).
    """

    def __init__(self, core: RelayCore, peer: Peer, catalog: TopicCatalog,
                 codec: Codec, session_id: str) -> None:
        self.core = core
        self.peer = peer
        self.catalog = catalog
        self.codec = codec
        self.session_id = session_id
        self.advertised: set[int] = set()
        self.subscriptions: dict[int, fx.Channel] = {}  # subscription id -> channel
        self._by_channel: dict[int, int] = {}  # channel id -> subscription id
        self._by_topic_type: dict[tuple[str, str], int] = {}  # -> subscription id
        self._topic_refs: dict[str, int] = {}  # core subscriptions, per exact topic
        self.client_channels: dict[int, fx.ClientChannel] = {}
        self.started = False
        self._perms: Permissions | None = None  # the permissions the channels were chosen by
        self.mismatched = 0  # frames of a subscribed topic with another type than its channel

    # -- start and channels -----------------------------------------------------------

    def start(self) -> None:
        """Send Server Info and the channels the viewer may receive (spec: "at least one
        Advertise message is always sent to new clients upon connection")."""
        perms = self.peer.perms
        assert perms is not None
        self.started = True
        self._perms = perms
        client_publish = any(r.op.allows_send() for r in perms.rules)
        self._push(fx.server_info(self.session_id, client_publish=client_publish))
        visible = [c for c in self.catalog.channels() if perms.may_receive(c.topic)]
        self.advertised.update(c.id for c in visible)
        self._push(fx.advertise(visible))

    def refresh(self) -> None:
        """Re-choose the channels if the permissions changed (an auth map reload gives the
        connection a new :class:`Permissions`): unadvertise what it may no longer receive
        (its subscriptions end), advertise what it now may. Cheap when nothing changed."""
        perms = self.peer.perms
        if not self.started or perms is None or perms is self._perms:
            return
        self._perms = perms
        visible = {c.id: c for c in self.catalog.channels() if perms.may_receive(c.topic)}
        gone = sorted(i for i in self.advertised if i not in visible)
        new = [c for i, c in visible.items() if i not in self.advertised]
        for channel_id in gone:
            sub_id = self._by_channel.get(channel_id)
            if sub_id is not None:
                self._unsubscribe(sub_id)
            self.advertised.discard(channel_id)
        if gone:
            self._push(fx.unadvertise(gone))
        if new:
            self.advertised.update(c.id for c in new)
            self._push(fx.advertise(new))

    def on_channel(self, channel: fx.Channel, added: bool) -> None:
        """A channel appeared or went (a :class:`TopicCatalog` listener)."""
        perms = self.peer.perms
        if not self.started or perms is None:
            return
        if added:
            if perms.may_receive(channel.topic) and channel.id not in self.advertised:
                self.advertised.add(channel.id)
                self._push(fx.advertise([channel]))
        elif channel.id in self.advertised:
            self.advertised.discard(channel.id)
            sub_id = self._by_channel.get(channel.id)
            if sub_id is not None:
                self._unsubscribe(sub_id)
            self._push(fx.unadvertise([channel.id]))

    # -- client messages --------------------------------------------------------------

    def on_text(self, text: str) -> None:
        """Handle one JSON text of the client (a bad one costs a Status, see
        :meth:`RelayCore.malformed`).

        Each item of a request (a channel subscribed or advertised, an id unsubscribed or
        unadvertised) is one control request of the identity's rate
        (``max_control_requests_per_s``, as a fleetctl ``/subscriptions`` frame): past
        it the rest of the request and what the connection sends meanwhile are
        discarded. Why: a request carries up to 1024 items, and 600 requests of refused
        channels and client channels held the event loop for 13 s (other clients' frames
        1.4 s late)."""
        peer, core = self.peer, self.core
        if peer.throttled:
            core.discard(peer)
            return
        try:
            request = fx.parse_request(text)
        except fx.ProtocolError as exc:
            core.malformed(peer, "malformed_frame", None, str(exc))
            return
        peer.malformed_in_row = 0
        if isinstance(request, fx.Subscribe):
            for sub_id, channel_id in request.subscriptions:
                if not core.allow_control(peer):
                    return
                self._subscribe(sub_id, channel_id)
        elif isinstance(request, fx.Unsubscribe):
            for sub_id in request.ids:
                if not core.allow_control(peer):
                    return
                self._unsubscribe(sub_id)
        elif isinstance(request, fx.ClientAdvertise):
            for channel in request.channels:
                if not core.allow_control(peer):
                    return
                self._client_advertise(channel)
        elif isinstance(request, fx.ClientUnadvertise):
            for channel_id in request.ids:
                if not core.allow_control(peer):
                    return
                self.client_channels.pop(channel_id, None)
        else:  # pragma: no cover - parse_request returns only the types above
            raise AssertionError(request)

    def on_binary(self, frame: bytes) -> None:
        """Handle one Client Message Data: publish it as a fleetctl frame (discarded
        while the connection is throttled, as a fleetctl connection's frames are)."""
        if self.peer.throttled:
            self.core.discard(self.peer)
            return
        try:
            channel_id, payload = fx.parse_client_data(frame)
        except fx.ProtocolError as exc:
            self.core.malformed(self.peer, "malformed_frame", None, str(exc))
            return
        channel = self.client_channels.get(channel_id)
        if channel is None:
            self.core.malformed(self.peer, "unknown_type", None,
                                f"client channel {channel_id} is not advertised")
            return
        try:
            msg = self.codec.registry.typestore.deserialize_cdr(bytes(payload),
                                                                 channel.schema_name)
            out = self.codec.encode(msg, channel.schema_name, channel.topic,
                                    publish_time_ns=time.time_ns())
        except Exception as exc:  # rosbags raises several types for a bad CDR payload
            self.core.malformed(self.peer, "malformed_frame", channel.topic,
                                f"not a CDR {channel.schema_name}: {type(exc).__name__}")
            return
        self.core.on_binary(self.peer, out)  # checks the send rules again, routes

    # -- server messages --------------------------------------------------------------

    def message(self, topic: str, converted: Converted | None) -> bytes | None:
        """The Message Data for a frame of *topic* popped from the outbound scheduler and
        *converted* (:mod:`.offload`), or ``None`` when it is not for a current
        subscription or does not complete a message."""
        if converted is None:
            return None
        sub_id = self._by_topic_type.get((topic, converted.type))
        if sub_id is None:
            self.mismatched += 1
            return None
        return fx.message_data(sub_id, converted.receive_time_ns, converted.cdr)

    @staticmethod
    def control(text: str) -> str | None:
        """Translate a control text from the outbound scheduler: ours pass, the core's
        errors become Status (error), the core's other frames are not sent."""
        if text.startswith('{"op"'):  # ours (messages.py writes "op" first)
            return text
        data: Any = json.loads(text)
        if data.get("type") == "error":
            topic = f" ({data['topic']})" if data.get("topic") else ""
            return fx.status(fx.ERROR, f"{data.get('code')}{topic}: {data.get('message')}")
        return None

    # -- helpers ----------------------------------------------------------------------

    def _push(self, text: str) -> None:
        self.peer.outbound.push_control(text)

    def _error(self, message: str) -> None:
        self._push(fx.status(fx.ERROR, message))

    def _subscribe(self, sub_id: int, channel_id: int) -> None:
        channel = self.catalog.channel(channel_id)
        if channel is None or channel_id not in self.advertised:
            self.core.send_error(self.peer, "subscription_refused", None,
                                 f"channel {channel_id} is not advertised to this connection")
            return
        if sub_id in self.subscriptions or channel_id in self._by_channel:
            self._error(f"subscription {sub_id} or channel {channel_id} is already in use")
            return
        topic = channel.topic
        if topic not in self._topic_refs and not self.core.subscribe(self.peer, _exact(topic),
                                                                      charge=False):
            return  # the core said why (an error frame, now a Status)
        self._topic_refs[topic] = self._topic_refs.get(topic, 0) + 1
        self.subscriptions[sub_id] = channel
        self._by_channel[channel_id] = sub_id
        self._by_topic_type[(topic, channel.schema_name)] = sub_id

    def _unsubscribe(self, sub_id: int) -> None:
        channel = self.subscriptions.pop(sub_id, None)
        if channel is None:
            return  # spec: ids of unknown subscriptions are ignored
        del self._by_channel[channel.id]
        del self._by_topic_type[(channel.topic, channel.schema_name)]
        refs = self._topic_refs[channel.topic] - 1
        if refs:
            self._topic_refs[channel.topic] = refs
        else:
            del self._topic_refs[channel.topic]
            self.core.unsubscribe(self.peer, _exact(channel.topic))

    def _client_advertise(self, channel: fx.ClientChannel) -> None:
        perms = self.peer.perms
        assert perms is not None
        if channel.encoding != "cdr":
            self._error(f"client channel {channel.id}: encoding {channel.encoding!r} is not "
                        "supported (cdr only)")
        elif not perms.may_send(channel.topic):
            self.core.send_error(self.peer, "unauthorized_send", channel.topic,
                                 f"no send permission on {channel.topic!r}")
        elif _known_type(self.codec, channel.schema_name) is None:
            self._error(f"client channel {channel.id}: unknown type {channel.schema_name!r}")
        elif (channel.id not in self.client_channels
              and len(self.client_channels) >= MAX_CLIENT_CHANNELS):
            self._error(f"more than {MAX_CLIENT_CHANNELS} client channels")
        else:
            type_name = _known_type(self.codec, channel.schema_name)
            assert type_name is not None
            self.client_channels[channel.id] = dataclasses.replace(channel,
                                                                   schema_name=type_name)


def _known_type(codec: Codec, name: str) -> str | None:
    """*name* as ``pkg/msg/Name`` if the registry knows it (Foxglove may send the ROS 1
    form ``pkg/Name``), else ``None``."""
    try:
        type_name = normalize_type(name)
    except WireError:
        return None
    return type_name if type_name in codec.registry.typestore.fielddefs else None


def _exact(topic: str) -> str:
    """A full-match pattern for exactly *topic* (RE2 accepts Python's escapes)."""
    return re.escape(topic)
