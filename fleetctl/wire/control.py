"""Robofleet control messages: subscriptions and robot status (thin helpers over the codec).

- ``amrl_msgs/msg/RobofleetSubscription {string topic_regex; uint8 action}`` on topic
  ``/subscriptions``; action 1 subscribes, 0 unsubscribes (Robofleet Section III-B).
- ``amrl_msgs/msg/RobofleetStatus {string status; bool is_ok; float32 battery_level;
  string location}`` on ``/<robot>/status``.
- ``fleetctl_msgs/msg/KeyframeRequest {string topic}`` on ``/keyframe_requests``: a viewer
  (or the server) asks the publisher of a video topic for a keyframe (docs/wire.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.errors import WireError

SUBSCRIPTION_TYPE = "amrl_msgs/msg/RobofleetSubscription"
STATUS_TYPE = "amrl_msgs/msg/RobofleetStatus"
SUBSCRIPTIONS_TOPIC = "/subscriptions"
ACTION_UNSUBSCRIBE = 0
ACTION_SUBSCRIBE = 1
KEYFRAME_REQUEST_TYPE = "fleetctl_msgs/msg/KeyframeRequest"
KEYFRAME_REQUESTS_TOPIC = "/keyframe_requests"
# RobofleetStatus.battery_level has no null: a robot that does not know its battery (no
# battery topic configured or heard) sends this.
UNKNOWN_BATTERY = -1.0


def known_battery(level: float | None) -> float | None:
    """Return *level*, or ``None`` when it means "unknown" (negative, NaN, infinite).

    What ``/robots``, ``fleetctl status`` and the page show for a robot without a battery
    topic: ``None`` (JSON null, a dash), never a level of -1 (-100 %).
    """
    if level is None or not math.isfinite(level) or level < 0:
        return None
    return level


@dataclass(frozen=True, slots=True)
class Subscription:
    """A decoded subscription request.

    Attributes:
        topic_regex: RE2 pattern, full-matched against topic names (not validated here).
        subscribe: True to subscribe, False to unsubscribe.
    """

    topic_regex: str
    subscribe: bool


@dataclass(frozen=True, slots=True)
class Status:
    """A decoded robot status.

    Attributes:
        robot: Robot name, the first segment of the topic (``husky1`` of
            ``/husky1/status``).
        topic: The topic it came on.
        status: Free-form status text.
        is_ok: The robot considers itself healthy.
        battery_level: Battery charge as reported (fraction 0..1 by convention;
            :data:`UNKNOWN_BATTERY` when the robot does not know it, see
            :func:`known_battery`).
        location: Free-form location text.
        publish_time_ns: Metadata publish time, ns since the epoch (0 if unset).
    """

    robot: str
    topic: str
    status: str
    is_ok: bool
    battery_level: float
    location: str
    publish_time_ns: int = 0


def status_topic(robot: str) -> str:
    """The status topic of *robot* (``/husky1/status``)."""
    return f"/{robot}/status"


def encode_subscription(
    topic_regex: str, subscribe: bool = True, *, codec: Codec | None = None
) -> bytes:
    """A subscription (or unsubscription) frame on ``/subscriptions``.

    Raises:
        WireError: The regex is not a string.
    """
    codec = codec or default_codec()
    cls = codec.registry.get(SUBSCRIPTION_TYPE).cls
    action = ACTION_SUBSCRIBE if subscribe else ACTION_UNSUBSCRIBE
    return codec.encode(cls(topic_regex, action), SUBSCRIPTION_TYPE, SUBSCRIPTIONS_TOPIC)


def decode_subscription(frame: bytes | memoryview, *, codec: Codec | None = None) -> Subscription:
    """Decode a subscription frame.

    Raises:
        WireError: Malformed frame, another type, or an action other than 0 or 1.
    """
    _meta, msg = (codec or default_codec()).decode_as(frame, SUBSCRIPTION_TYPE)
    if msg.action not in (ACTION_SUBSCRIBE, ACTION_UNSUBSCRIBE):
        raise WireError(f"RobofleetSubscription.action must be 0 or 1, got {msg.action}")
    return Subscription(msg.topic_regex, msg.action == ACTION_SUBSCRIBE)


def encode_status(
    robot: str,
    *,
    status: str,
    is_ok: bool,
    battery_level: float,
    location: str = "",
    publish_time_ns: int = 0,
    seq: int = 0,
    codec: Codec | None = None,
) -> bytes:
    """A status frame of *robot* on ``/<robot>/status``.

    Raises:
        WireError: A value does not fit its field.
    """
    codec = codec or default_codec()
    cls = codec.registry.get(STATUS_TYPE).cls
    msg = cls(status, bool(is_ok), float(battery_level), location)
    return codec.encode(
        msg, STATUS_TYPE, status_topic(robot), publish_time_ns=publish_time_ns, seq=seq
    )


def decode_status(frame: bytes | memoryview, *, codec: Codec | None = None) -> Status:
    """Decode a status frame.

    Raises:
        WireError: Malformed frame, another type, or a topic not of the form
            ``/<robot>/status``.
    """
    meta, msg = (codec or default_codec()).decode_as(frame, STATUS_TYPE)
    parts = meta.topic.split("/")
    if len(parts) != 3 or parts[0] or not parts[1] or parts[2] != "status":
        raise WireError(f"status frame on {meta.topic!r}: expected /<robot>/status")
    return Status(
        robot=parts[1],
        topic=meta.topic,
        status=msg.status,
        is_ok=bool(msg.is_ok),
        battery_level=float(msg.battery_level),
        location=msg.location,
        publish_time_ns=meta.publish_time_ns,
    )


def encode_keyframe_request(topic: str, *, publish_time_ns: int = 0, seq: int = 0,
                            codec: Codec | None = None) -> bytes:
    """A keyframe request for video *topic* on ``/keyframe_requests`` (no_drop: the
    server forwards each as is, and a latest-only slot would let one camera's request
    replace another's).

    Raises:
        WireError: *topic* is not a string.
    """
    codec = codec or default_codec()
    cls = codec.registry.get(KEYFRAME_REQUEST_TYPE).cls
    return codec.encode(cls(topic), KEYFRAME_REQUEST_TYPE, KEYFRAME_REQUESTS_TOPIC,
                        no_drop=True, publish_time_ns=publish_time_ns, seq=seq)


def decode_keyframe_request(frame: bytes | memoryview, *, codec: Codec | None = None) -> str:
    """The video topic a keyframe request names.

    Raises:
        WireError: Malformed frame, another type, or an empty topic.
    """
    _meta, msg = (codec or default_codec()).decode_as(frame, KEYFRAME_REQUEST_TYPE)
    if not msg.topic:
        raise WireError("KeyframeRequest.topic is empty")
    return str(msg.topic)
