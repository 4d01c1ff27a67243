"""What each scenario's robot publishes, and the client config (and baseline) that sends it.

Parameters are the issue's (Robofleet section IV, Pound section 6); where it is silent the
choice is documented here and in docs/e2e.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from fleetctl.client.config import MAX_FRAGMENT_BYTES
from fleetctl.errors import FleetError

ROBOT = "robot1"


@dataclass(frozen=True)
class TopicLoad:
    """One local topic the load publisher publishes.

    Attributes:
        topic: Local ROS topic (the wire topic is ``/robot1<topic>``).
        type: ROS 2 type (one of :data:`fleetctl.e2e.payloads.BUILDERS`).
        rate_hz: Publish rate (Hz).
        size_bytes: Payload size (bytes, approximate for fixed-size types).
        priority: Client priority (Algorithm 2 weight).
        no_drop: Sent reliably by the client.
        video_max_kbps: When above 0, the client sends this camera as h264 video
            (``video: {codec: h264, max_bitrate_kbps: ...}``) instead of raw images.
    """

    topic: str
    type: str
    rate_hz: float
    size_bytes: int
    priority: float = 1.0
    no_drop: bool = False
    video_max_kbps: int = 0

    @property
    def is_video(self) -> bool:
        """The client sends this topic as video."""
        return self.video_max_kbps > 0

    @property
    def remote_topic(self) -> str:
        """The topic on the wire."""
        return f"/{ROBOT}{self.topic}"


@dataclass(frozen=True)
class Profile:
    """A scenario's load and client settings.

    Attributes:
        name: Profile name (``--profile`` of the load publisher).
        topics: What is published.
        max_fragment_bytes: Client fragment size (bytes).
        scheduler: The client's ``limits.scheduler`` (``adaptive`` or ``robofleet``).
        spread_phases: The load publisher starts the topics' timers at fixed phases,
            spread evenly over the shortest period (:func:`fleetctl.e2e.load.phase_schedule`),
            instead of wherever each timer's creation falls. For side-by-side runs: every
            robot of every stack then publishes at the same phases.
    """

    name: str
    topics: tuple[TopicLoad, ...]
    max_fragment_bytes: int = 16384
    scheduler: str = "adaptive"
    spread_phases: bool = False

    def topic(self, local: str) -> TopicLoad:
        """The entry of local topic *local*.

        Raises:
            FleetError: no such topic.
        """
        for t in self.topics:
            if t.topic == local:
                return t
        raise FleetError(f"profile {self.name}: no topic {local}")


_SCAN = TopicLoad("/scan", "sensor_msgs/msg/LaserScan", 10.0, 8640, priority=2.0)
_POSE = TopicLoad("/pose", "geometry_msgs/msg/PoseStamped", 10.0, 0, priority=4.0)
_IMAGE = TopicLoad("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", 2.0, 75_000)
_EVENTS = TopicLoad("/events", "std_msgs/msg/String", 10.0, 200, priority=1.0, no_drop=True)
_POINTS = TopicLoad("/points", "sensor_msgs/msg/PointCloud2", 5.0, 150_000, priority=0.5)
# A raw 640x480 rgb8 camera at 15 Hz (13.8 MB/s on the robot) sent as h264 video. Its
# priority is the compressed image's; the bitrate ceilings are chosen so that the video
# fits the dropout's 4 Mbit/s beside the other topics, and in the ramp so that at 100 Mbit/s
# it runs at 3 Mbit/s, more than 4 Mbit/s leaves it: it has to follow the link down.
_CAMERA = TopicLoad("/camera/image_raw", "sensor_msgs/msg/Image", 15.0, 640 * 480 * 3,
                    video_max_kbps=600)

PROFILES: dict[str, Profile] = {
    "dropout": Profile("dropout", (_SCAN, _POSE, _IMAGE, _EVENTS, _CAMERA)),
    # Pound: small fragments bound how long an urgent message waits behind a large one
    # (4 KB at 6 Mbit/s is 5.5 ms on the wire; the default 16 KB would be 22 ms).
    "priority": Profile("priority", (
        TopicLoad("/high", "sensor_msgs/msg/CompressedImage", 50.0, 1024, priority=10.0),
        TopicLoad("/low", "sensor_msgs/msg/CompressedImage", 1000 / 150, 65_536, priority=1.0),
    ), max_fragment_bytes=4096),
    "multi-consumer": Profile("multi-consumer", (replace(_POINTS, priority=1.0),)),
    # Issue 19's side-by-side load against zenoh: a 720-beam scan (ranges + intensities,
    # 5,760 bytes) at 10 Hz and a pose at 20 Hz, nothing else. Phases fixed (since
    # 2026-12-08): where each robot's timers happened to start put its scans 3.4 ms
    # before to 14 ms after a pose, and a stack's scan p50 moved ~0.6 ms with it.
    "peer": Profile("peer", (replace(_SCAN, size_bytes=5760),
                             replace(_POSE, rate_hz=20.0)), spread_phases=True),
    # Issue 19 for large messages: a camera's JPEGs (100 KB of random bytes at 3 Hz,
    # 2.4 Mbit/s) beside a 20 Hz pose on a 4 Mbit/s link (peerlarge.py).
    "peer-large": Profile("peer-large", (
        replace(_POSE, rate_hz=20.0),
        replace(_IMAGE, rate_hz=3.0, size_bytes=100_000))),
    # Issue 15's replica-failure: what the viewers watch (a 20 Hz pose, latest-only) and
    # what must arrive whole (10 Hz events, no_drop) while a relay replica dies.
    "replica-failure": Profile("replica-failure", (replace(_POSE, rate_hz=20.0), _EVENTS)),
    "ramp": Profile("ramp", (replace(_POSE, priority=10.0), _SCAN, _IMAGE, _POINTS,
                             replace(_CAMERA, video_max_kbps=3000))),
}


def profile(name: str) -> Profile:
    """The profile called *name*.

    Raises:
        FleetError: unknown name.
    """
    if name not in PROFILES:
        raise FleetError(f"unknown load profile {name!r}; choose from {sorted(PROFILES)}")
    return PROFILES[name]


def all_no_drop(p: Profile) -> Profile:
    """Baseline of dropout and ramp: every topic no_drop (rosbridge-like queueing)."""
    return replace(p, topics=tuple(replace(t, no_drop=True) for t in p.topics))


def robofleet_like(p: Profile) -> Profile:
    """Baseline of priority: Robofleet's scheduling, every topic the same priority.

    ``limits.scheduler: robofleet`` sends whole frames with one frame in flight (n_T = 1).
    """
    return replace(p, topics=tuple(replace(t, priority=1.0) for t in p.topics),
                   max_fragment_bytes=MAX_FRAGMENT_BYTES, scheduler="robofleet")


def client_config(p: Profile, server_url: str | list[str]) -> dict[str, Any]:
    """The ``client.yaml`` document (docs/design.md section 5) that sends *p*'s topics."""
    return {
        "server_url": server_url,
        "robot_name": ROBOT,
        "publish": [
            {"topic": t.topic, "type": t.type, "priority": t.priority, "rate_limit_hz": None,
             "no_drop": t.no_drop,
             **({"video": {"codec": "h264", "max_bitrate_kbps": t.video_max_kbps}}
                if t.is_video else {})}
            for t in p.topics
        ],
        "status": {"period_s": 1.0},
        "limits": {"max_fragment_bytes": p.max_fragment_bytes, "scheduler": p.scheduler},
    }
