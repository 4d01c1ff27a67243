"""Two real relay replicas on real nats-server processes, real WebSocket clients."""

from __future__ import annotations

import asyncio
import copy
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.config import ClusterStartError
from fleetctl.server.cluster.sharedsessions import SharedSessions
from tests.server.cluster.conftest import fanout
from tests.server.cluster.natsproc import NatsServer
from tests.server.conftest import (
    ALICE_TOKEN,
    AUTH,
    BOB_TOKEN,
    auth_map,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.support import decode_text, string_frame

pytestmark = pytest.mark.slow


def shared(srv: RelayServer) -> SharedSessions:
    found = srv.core.sessions.shared
    assert found is not None
    return found


async def no_binary(ws: object, within_s: float = 0.3) -> bool:
    """True if no binary frame arrives within *within_s* (checks an absence)."""
    try:
        await next_binary(ws, within_s)  # type: ignore[arg-type]
    except TimeoutError:
        return True
    return False


async def until_crossing(sender: Any, receiver: Any, topic: str) -> None:
    """Send probes on *topic* until one reaches *receiver*: the subscription has reached
    the sender's NATS server (interest crosses cluster routes asynchronously)."""
    for _ in range(400):  # 20 s at most
        await sender.send(string_frame(topic, "probe"))
        try:
            await next_binary(receiver, 0.05)
            return
        except TimeoutError:
            continue
    raise AssertionError(f"no frame on {topic} crossed the replicas")


async def drain(ws: Any) -> None:
    """Read binary frames until none arrives for a moment (late probes)."""
    while not await no_binary(ws, 0.2):
        pass


async def chat_texts(ws: Any, n: int) -> list[str]:
    """The texts of the next *n* frames on /husky1/chat (probes skipped)."""
    from fleetctl.wire.metadata import read_root

    texts: list[str] = []
    while len(texts) < n:
        frame = await next_binary(ws, 15.0)
        if read_root(frame)[0].topic == "/husky1/chat":
            texts.append(decode_text(frame))
    return texts


async def test_frame_crosses_replicas_once(replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with client(a, source="127.0.0.2") as robot, \
            client(b, token=ALICE_TOKEN) as remote, client(a, token=ALICE_TOKEN) as local:
        await next_json(robot, "welcome")
        # Two overlapping patterns on B's side: one NATS subscription, one delivery.
        assert (await subscribe(remote, "/husky1/.*"))["type"] == "subscribed"
        assert (await subscribe(remote, "/husky1/chat"))["type"] == "subscribed"
        assert (await subscribe(local, "/husky1/chat"))["type"] == "subscribed"
        await wait_for(lambda: fanout(b).subscribed == {"fleetctl.husky1.>"})
        # ... and B reads the same subjects of the no_drop stream, A only its chat topic.
        await wait_for(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky1.>",)
                       and shared(a).remote_subjects == ("fleetctl_nd.husky1.chat",))
        await until_crossing(robot, remote, "/husky1/probe")
        await drain(remote)
        # Probes sent before B's interest crossed the route were published and never
        # received: count from here.
        published, received = fanout(a).published, fanout(b).received
        stream_a, stream_b = shared(a).counters, shared(b).counters
        stored, crossed = stream_a["stored"], stream_b["remote"]
        for i in range(20):  # no_drop: a slow reader would otherwise get only the latest
            await robot.send(string_frame("/husky1/chat", f"m{i}", no_drop=True))
        assert await chat_texts(remote, 20) == [f"m{i}" for i in range(20)]
        assert await chat_texts(local, 20) == [f"m{i}" for i in range(20)]
        # no_drop frames cross through the sessions' stream, not core NATS.
        await wait_for(lambda: stream_b["remote"] - crossed == 20
                       and stream_a["stored"] - stored == 20, 15.0)
        assert (fanout(b).received, fanout(a).published) == (received, published)
        # Once each: B wrote 20 chat frames (to its one subscriber), A 20 (to its local one).
        assert b.metrics.messages_out["/husky1/chat"] == 20
        assert a.metrics.messages_out["/husky1/chat"] == 20
        assert fanout(a).received == 0  # A never gets its own frames back (no_echo)
        assert stream_a["remote"] == 0  # ... nor from the stream (it skips its own)
        assert a.metrics.messages_in["/husky1/chat"] == 20


async def test_acl_applies_on_the_receiving_replica(replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with client(a, token=ALICE_TOKEN) as alice, client(b, token=BOB_TOKEN) as bob, \
            client(b, token=ALICE_TOKEN) as other:
        assert (await subscribe(bob, ".*"))["type"] == "subscribed"  # filtered per delivery
        # Bob's rules narrow B's interest (receive /husky1/.*); another viewer on B
        # brings /elsewhere/ frames to B too, which Bob's `.*` matches.
        assert (await subscribe(other, "/elsewhere/.*"))["type"] == "subscribed"
        await wait_for(lambda: fanout(b).subscribed == {"fleetctl.husky1.>",
                                                        "fleetctl.elsewhere.>"})
        await until_crossing(alice, bob, "/husky1/probe")
        await until_crossing(alice, other, "/elsewhere/probe")
        await drain(bob)
        before = fanout(b).received
        await alice.send(string_frame("/elsewhere/x", "not for bob"))
        await alice.send(string_frame("/husky1/marker", "for bob"))
        assert decode_text(await next_binary(bob)) == "for bob"
        assert await no_binary(bob)
        await wait_for(lambda: fanout(b).received == before + 2)  # both came; one refused


async def test_receive_rules_keep_unreceivable_frames_home(
        replicas: tuple[RelayServer, ...], nats_cluster: list[NatsServer]) -> None:
    """The page subscribes to `.*` with a token that may receive one robot: the other
    robot's frames are not published to NATS at all (docs/scaling.md, "Interest narrowed
    by receive rules")."""
    a, b = replicas
    board = fanout(a).remote_interest
    assert board is not None
    async with client(a, source="127.0.0.2") as husky1, \
            client(a, source="127.0.0.3") as husky2, client(b, token=BOB_TOKEN) as viewer:
        for ws in (husky1, husky2, viewer):
            await next_json(ws, "welcome")
        assert (await subscribe(viewer, ".*"))["type"] == "subscribed"
        await wait_for(lambda: fanout(b).subscribed == {"fleetctl.husky1.>"})
        await wait_for(lambda: fleet_subjects(nats_cluster[1]) == ["fleetctl.husky1.>"])
        await wait_for(lambda: board.known() == {"relay-b": {"fleetctl.husky1.>"}})
        await until_crossing(husky1, viewer, "/husky1/probe")
        await drain(viewer)
        published, unwanted, received = (fanout(a).published, fanout(a).unwanted,
                                         fanout(b).received)
        for i in range(FRAMES_EACH):
            await husky1.send(string_frame("/husky1/scan", f"h1-{i}"))
            await husky2.send(string_frame("/husky2/scan", f"h2-{i}"))
        # husky1's frames cross; husky2's are not even published.
        await wait_for(lambda: fanout(a).published - published == FRAMES_EACH
                       and fanout(a).unwanted - unwanted == FRAMES_EACH, 15.0)
        await wait_for(lambda: fanout(b).received - received == FRAMES_EACH, 15.0)
        assert a.metrics.messages_in["/husky2/scan"] == FRAMES_EACH
        assert fanout(b).interest.counters["narrowed"] == 1


FRAMES_EACH = 200


async def test_an_auth_reload_moves_the_interest(replicas: tuple[RelayServer, ...]) -> None:
    """Bob's rules change live: B's subscription and A's view of it follow, and the
    robot he may now receive crosses."""
    a, b = replicas
    board = fanout(a).remote_interest
    assert board is not None
    async with client(a, source="127.0.0.3") as husky2, client(b, token=BOB_TOKEN) as viewer:
        await next_json(husky2, "welcome")
        assert (await subscribe(viewer, ".*"))["type"] == "subscribed"
        await wait_for(lambda: board.known() == {"relay-b": {"fleetctl.husky1.>"}})
        raw = copy.deepcopy(AUTH)
        bob = next(i for i in raw["identities"] if i["name"] == "bob")
        bob["rules"] = [{"topic": "/husky2/.*", "op": "receive"}]
        assert b.core.reload_auth(auth_map(raw)) == (1, 0)
        await wait_for(lambda: fanout(b).subscribed == {"fleetctl.husky2.>"})
        await wait_for(lambda: board.known() == {"relay-b": {"fleetctl.husky2.>"}})
        await until_crossing(husky2, viewer, "/husky2/scan")
        # A probe sent after the one that crossed may still be on its way into A; A
        # answers husky2's ping only after taking every frame before it.
        await asyncio.wait_for(await husky2.ping(), 5.0)
        # ... and back: husky2's frames stay home again (A's view trusted: in doubt, it
        # would publish everything).
        assert b.core.reload_auth(auth_map(AUTH)) == (1, 0)
        await wait_for(lambda: board.trusted()
                       and board.known() == {"relay-b": {"fleetctl.husky1.>"}})
        unwanted, published = fanout(a).unwanted, fanout(a).published
        await husky2.send(string_frame("/husky2/scan", "not wanted"))
        await asyncio.wait_for(await husky2.ping(), 5.0)
        assert (fanout(a).unwanted - unwanted, fanout(a).published - published) == (1, 0), (
            f"trusted {board.trusted()}, known {board.known()}, {board.counters}")


def fleet_subjects(node: NatsServer) -> list[str]:
    """B's topic subscriptions on *node* (not its control subject, always held)."""
    subjects = node.client_subjects("relay-b")
    assert "fleetctl.~ctl.keyframe" in subjects
    return [s for s in subjects
            if s.startswith("fleetctl.") and not s.startswith("fleetctl.~ctl.")]


async def test_no_interest_no_frames(replicas: tuple[RelayServer, ...],
                                     nats_cluster: list[NatsServer]) -> None:
    a, b = replicas
    board = fanout(a).remote_interest
    assert board is not None
    async with client(a, source="127.0.0.2") as robot, client(b, token=ALICE_TOKEN) as viewer:
        await next_json(robot, "welcome")
        await next_json(viewer, "welcome")
        assert fanout(b).subscribed == frozenset()
        # A knows that B wants nothing: it does not even publish.
        await wait_for(lambda: board.trusted() and board.known() == {"relay-b": frozenset()})
        for i in range(50):
            await robot.send(string_frame("/husky1/chat", f"m{i}"))
        await wait_for(lambda: fanout(a).unwanted == 50)
        assert fanout(a).published == 0
        assert (await subscribe(viewer, "/husky1/status"))["type"] == "subscribed"
        await wait_for(lambda: fanout(b).subscribed == {"fleetctl.husky1.status"})
        # What NATS itself holds for B: only that fleet subject (besides the inboxes of
        # the shared state's KV watches and JetStream API replies, and the replicas'
        # control subject).
        await wait_for(lambda: fleet_subjects(nats_cluster[1]) == ["fleetctl.husky1.status"])
        await wait_for(lambda: board.known() == {"relay-b": {"fleetctl.husky1.status"}})
        await robot.send(string_frame("/husky1/chat", "still not wanted"))
        await wait_for(lambda: fanout(a).unwanted == 51)
        assert fanout(a).published == 0
        assert fanout(b).received == 0
        # What B asked for is published, and crosses.
        await until_crossing(robot, viewer, "/husky1/status")
        assert fanout(a).published > 0 and fanout(b).received > 0
        # Interest leaves with the subscriber.
        await viewer.send(_unsubscribe("/husky1/status"))
        await next_json(viewer, "unsubscribed")
        await wait_for(lambda: fanout(b).subscribed == frozenset())
        await wait_for(lambda: fleet_subjects(nats_cluster[1]) == [])
        await wait_for(lambda: board.known() == {"relay-b": frozenset()})
        unwanted = fanout(a).unwanted
        await robot.send(string_frame("/husky1/status", "nobody asks any more"))
        await wait_for(lambda: fanout(a).unwanted == unwanted + 1)


async def test_nats_lost_and_back(tmp_path: object, make_replica: Callable[..., RelayServer],
                                  nats_server: NatsServer) -> None:
    a = make_replica("relay-a", [nats_server.url])
    b = make_replica("relay-b", [nats_server.url])
    async with a, b, client(a, source="127.0.0.2") as robot, \
            client(a, token=ALICE_TOKEN) as local, client(b, token=ALICE_TOKEN) as remote:
        await next_json(robot, "welcome")
        for ws in (local, remote):
            assert (await subscribe(ws, "/husky1/chat"))["type"] == "subscribed"
        await until_crossing(robot, remote, "/husky1/chat")
        await drain(local)
        await drain(remote)

        nats_server.stop()
        await wait_for(lambda: not fanout(a).connected and not fanout(b).connected)
        await robot.send(string_frame("/husky1/chat", "during"))
        assert decode_text(await next_binary(local)) == "during"  # local delivery goes on
        await wait_for(lambda: fanout(a).dropped.get("disconnected", 0) >= 1)

        nats_server.start()
        await wait_for(lambda: fanout(a).connected and fanout(b).connected, 15.0)
        assert await no_binary(remote, 0.1)  # the frame sent while NATS was away is gone
        # B re-subscribed on reconnect: publish until one arrives (its SUB may trail A's).
        for i in range(100):
            await robot.send(string_frame("/husky1/chat", f"after{i}"))
            try:
                text = decode_text(await next_binary(remote, 0.1))
                break
            except TimeoutError:
                continue
        else:
            raise AssertionError("cross-replica delivery did not resume")
        assert text.startswith("after")
        assert fanout(a).reconnects >= 1
    text_metrics = a.metrics.render((), (), list(fanout(a).metric_families()))
    assert 'fleetctl_cluster_dropped_total{reason="disconnected"}' in text_metrics


async def test_nats_unreachable_at_start(make_replica: Callable[..., RelayServer]) -> None:
    from tests.server.cluster.natsproc import free_port

    replica = make_replica("relay-a", [f"nats://127.0.0.1:{free_port()}"],
                           connect_timeout_s=0.5)
    with pytest.raises(ClusterStartError, match=r"cluster\.nats_urls.*cannot reach NATS"):
        await asyncio.wait_for(replica.start(), 10)


async def test_wrong_credentials_refused(tmp_path: object, make_replica: Callable[..., RelayServer],
                                         caplog: pytest.LogCaptureFixture) -> None:
    from fleetctl.server.cluster.config import NatsCredentials

    work = Path(str(tmp_path))
    server = NatsServer("auth", work, authorization={"user": "relay", "password": "right-pw"})
    server.start()
    try:
        (work / "wrong").write_text("wrong-pw\n")
        (work / "right").write_text("right-pw\n")
        bad = make_replica("relay-a", [server.url], connect_timeout_s=5.0,
                           credentials=NatsCredentials(user="relay",
                                                       password_file=work / "wrong"))
        with pytest.raises(ClusterStartError, match=r"cluster\.credentials.*refused"):
            await asyncio.wait_for(bad.start(), 10)
        assert "refused its credentials" in caplog.text
        assert "wrong-pw" not in caplog.text
        good = make_replica("relay-b", [server.url],
                            credentials=NatsCredentials(user="relay", password_file=work / "right"))
        async with good:
            assert fanout(good).connected
    finally:
        server.stop()


def _unsubscribe(pattern: str) -> bytes:
    from fleetctl.wire.control import encode_subscription

    return encode_subscription(pattern, subscribe=False)


def test_cli_exits_naming_the_field(tmp_path: Path) -> None:
    """`fleetctl server` with NATS down: one line naming file and field, non-zero exit."""
    from tests.server.cluster.natsproc import free_port

    (tmp_path / "auth.yaml").write_text("version: 1\nidentities: []\n")
    config = tmp_path / "server.yaml"
    config.write_text("auth_map: auth.yaml\nlisten_host: 127.0.0.1\nlisten_port: 0\n"
                      "database: null\ncluster:\n  name: relay-a\n"
                      f"  nats_urls: [nats://127.0.0.1:{free_port()}]\n"
                      "  connect_timeout_s: 0.5\n")
    done = subprocess.run(
        [sys.executable, "-c", "from fleetctl.cli.main import main; raise SystemExit(main())",
         "server", "-c", str(config)], capture_output=True, text=True, timeout=60,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert done.returncode != 0
    assert f"{config}: field 'cluster.nats_urls': cannot reach NATS" in done.stderr
    assert "Traceback" not in done.stderr


async def test_one_nats_node_lost_replicas_keep_relaying(
        make_replica: Callable[..., RelayServer], nats_cluster: list[NatsServer]) -> None:
    """Replicas list every node; killing B's node moves B to another, and frames flow."""
    urls = [n.url for n in nats_cluster]
    a = make_replica("relay-a", [urls[0], urls[2]])
    b = make_replica("relay-b", [urls[1], urls[2]])
    async with a, b, client(a, source="127.0.0.2") as robot, \
            client(b, token=ALICE_TOKEN) as remote:
        await next_json(robot, "welcome")
        assert (await subscribe(remote, "/husky1/chat"))["type"] == "subscribed"
        await until_crossing(robot, remote, "/husky1/chat")
        nats_cluster[1].stop()
        await wait_for(lambda: fanout(b).reconnects >= 1, 15.0)
        await until_crossing(robot, remote, "/husky1/chat")


def _video_frame(topic: str) -> bytes:
    import numpy as np

    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.samples import header

    codec = default_codec()
    name = "foxglove_msgs/msg/CompressedVideo"
    msg = codec.registry.get(name).cls(header(codec.registry, "cam").stamp, "cam",
                                       np.zeros(64, dtype=np.uint8), "h264")
    return codec.encode(msg, name, topic, seq=1)


async def test_a_keyframe_request_reaches_the_publisher_on_another_replica(
        replicas: tuple[RelayServer, ...]) -> None:
    from fleetctl.wire.control import (
        KEYFRAME_REQUESTS_TOPIC,
        decode_keyframe_request,
        encode_keyframe_request,
    )
    from fleetctl.wire.metadata import read_metadata

    a, b = replicas
    async with client(a, source="127.0.0.2") as robot, \
            client(b, token=ALICE_TOKEN) as viewer, client(a, token=ALICE_TOKEN) as wide:
        await next_json(robot, "welcome")
        await next_json(viewer, "welcome")
        # A consumer of everything on A: its replica subscribes to the whole fleet
        # subject, which the replicas' control subject is under. (Before the video
        # topic is known: a subscription to a known one makes A ask by itself.)
        assert (await subscribe(wide, ".*"))["type"] == "subscribed"
        await wait_for(lambda: fanout(a).subscribed == {"fleetctl.>"})
        await robot.send(_video_frame("/husky1/camera"))  # A learns its video publisher
        await wait_for(lambda: a.core.keyframes.publisher("/husky1/camera") is not None)
        request = encode_keyframe_request("/husky1/camera")
        for _ in range(100):  # B's viewer asks; A may only hear it once B's NATS link is up
            await viewer.send(request)
            try:
                frame = await next_binary(robot, 0.2)
            except TimeoutError:
                continue
            break
        else:
            raise AssertionError("no keyframe request crossed the replicas")
        assert read_metadata(frame).topic == KEYFRAME_REQUESTS_TOPIC
        assert decode_keyframe_request(frame) == "/husky1/camera"
        assert b.metrics.keyframe_requests.get("to_replicas", 0) >= 1
        assert a.metrics.keyframe_requests.get("forwarded", 0) >= 1
        # A request for a topic nobody publishes goes to the replicas and ends there.
        await viewer.send(encode_keyframe_request("/husky1/nobody"))
        assert await no_binary(robot, 0.5)
        # The consumer of everything on A never got the control messages as frames.
        seen: list[str] = []
        while True:
            try:
                seen.append(read_metadata(await next_binary(wide, 0.3)).topic)
            except TimeoutError:
                break
        assert KEYFRAME_REQUESTS_TOPIC not in seen, seen
        assert fanout(a).received == 0


async def test_a_viewer_subscribing_on_another_replica_gets_a_keyframe_asked_for(
        replicas: tuple[RelayServer, ...]) -> None:
    """The server asks by itself when a viewer subscribes to a camera, also when the
    camera's robot is on another replica (the viewer does not ask here)."""
    from fleetctl.wire.control import KEYFRAME_REQUESTS_TOPIC, decode_keyframe_request
    from fleetctl.wire.metadata import read_metadata

    a, b = replicas
    async with client(a, source="127.0.0.2") as robot, \
            client(b, token=ALICE_TOKEN) as viewer, client(b, token=ALICE_TOKEN) as later:
        await next_json(robot, "welcome")
        await robot.send(_video_frame("/husky1/camera"))
        await wait_for(lambda: a.core.keyframes.publisher("/husky1/camera") is not None)
        assert (await subscribe(viewer, "/husky1/camera"))["type"] == "subscribed"

        async def request_reaches_robot() -> None:
            for _ in range(200):  # delta frames until B's interest is in place
                await robot.send(_video_frame("/husky1/camera"))
                try:
                    frame = await next_binary(robot, 0.05)
                except TimeoutError:
                    continue
                assert read_metadata(frame).topic == KEYFRAME_REQUESTS_TOPIC
                assert decode_keyframe_request(frame) == "/husky1/camera"
                return
            raise AssertionError("no keyframe request reached the robot on A")

        await request_reaches_robot()  # B saw the camera's first frame: it asked
        assert b.metrics.keyframe_requests.get("auto_to_replicas") == 1
        assert "/husky1/camera" in b.core.remote_video
        # A second viewer on B, the camera already flowing: B asks when it subscribes.
        await asyncio.sleep(a.config.limits.keyframe_request_interval_s)  # A's rate limit
        assert (await subscribe(later, "/husky1/camera"))["type"] == "subscribed"
        await request_reaches_robot()
        assert b.metrics.keyframe_requests.get("auto_to_replicas") == 2
