"""Unit tests of the keyframe request router (no relay, no sockets)."""

from __future__ import annotations

from fleetctl.server.keyframes import KeyframeRouter
from fleetctl.server.metrics import Metrics
from tests.support import ManualClock


def make(**kw: int) -> tuple[KeyframeRouter[str], ManualClock, Metrics]:
    clock, metrics = ManualClock(), Metrics()
    return KeyframeRouter(0.25, clock, metrics, **kw), clock, metrics


def test_routes_to_the_last_publisher() -> None:
    router, _clock, _ = make()
    router.note_publisher("/r1/cam", "conn-a")
    router.note_publisher("/r1/cam", "conn-b")  # a reconnected robot publishes now
    assert router.route("/r1/cam") == "conn-b"


def test_at_most_one_forward_per_topic_per_interval() -> None:
    router, clock, metrics = make()
    router.note_publisher("/r1/cam", "a")
    router.note_publisher("/r1/cam2", "a")
    assert router.route("/r1/cam") == "a"
    clock.now_s += 0.2
    assert router.route("/r1/cam") is None  # within 0.25 s
    assert router.route("/r1/cam2") == "a"  # another topic has its own interval
    clock.now_s += 0.06
    assert router.route("/r1/cam") == "a"
    assert metrics.keyframe_requests == {"rate_limited": 1}


def test_unknown_or_forgotten_publisher_routes_nowhere() -> None:
    router, _, metrics = make()
    assert router.route("/r1/cam") is None
    router.note_publisher("/r1/cam", "a")
    router.note_publisher("/r2/cam", "b")
    router.forget("a")
    assert router.route("/r1/cam") is None
    assert router.video_topics() == ["/r2/cam"]
    assert metrics.keyframe_requests == {"no_publisher": 2}


def test_topic_bound_forgets_the_least_recently_published() -> None:
    router, _, _ = make(max_topics=2)
    for i in range(3):
        router.note_publisher(f"/r1/cam{i}", "a")
    assert router.video_topics() == ["/r1/cam1", "/r1/cam2"]


def test_the_servers_own_request_is_encoded_once_and_forgotten_with_its_topic() -> None:
    from fleetctl.server.regex import compile_full
    from fleetctl.wire.control import encode_keyframe_request

    router, _, _ = make(max_topics=2)
    router.note_publisher("/r1/cam0", "a")
    frame = router.request_frame("/r1/cam0")
    assert frame == encode_keyframe_request("/r1/cam0")
    assert router.request_frame("/r1/cam0") is frame  # kept while the topic is
    router.note_publisher("/r1/cam1", "a")
    router.note_publisher("/r1/cam2", "a")  # /r1/cam0 forgotten, its request too
    assert router.request_frame("/r1/cam0") is not frame
    assert router.candidates([compile_full("/r1/.*")]) == ["/r1/cam1", "/r1/cam2"]
    router.note_publisher("/r1/cam1", "b")  # a new publisher: last, as in video_topics
    assert router.candidates([compile_full("/r1/.*")]) == router.video_topics() == [
        "/r1/cam2", "/r1/cam1"]
    router.forget("b")
    assert router.candidates([compile_full("/r1/cam1")]) == []
