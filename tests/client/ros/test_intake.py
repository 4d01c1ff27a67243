"""LoopIntake against the installed rclpy and rmw: woken by the middleware, taken on the loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from fleetctl.client.ros import intake as intake_module  # noqa: E402
from fleetctl.client.ros.executor import NodeExecutor  # noqa: E402
from fleetctl.client.ros.intake import LoopIntake, LoopServed, Wakeups, load_wakeups  # noqa: E402
from fleetctl.client.ros.qos import AdaptiveSubscription  # noqa: E402
from tests.client.ros.harness import spinning  # noqa: E402
from tests.support import wait_until  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 36  # this engineer's range is 20-39; 36 is reserved for this file
QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


class Nodes:
    """A node under test and a peer that publishes, in one context."""

    def __init__(self, context: Context) -> None:
        self.context = context
        self.node = Node("intake_under_test", context=context, start_parameter_services=False)
        self.peer = Node("intake_peer", context=context)

    def publisher(self, topic: str, qos: QoSProfile = QOS) -> Any:
        from std_msgs.msg import String

        return self.peer.create_publisher(String, topic, qos)


@pytest.fixture
async def nodes() -> AsyncIterator[Nodes]:
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    n = Nodes(context)
    try:
        yield n
    finally:
        n.node.destroy_node()
        n.peer.destroy_node()
        context.try_shutdown()


@contextlib.contextmanager
def executor_spinning(nodes: Nodes) -> Iterator[NodeExecutor]:
    """The client's executor spinning the node under test in a thread, stopped on exit."""
    with spinning(nodes.node, nodes.context) as executor:
        yield executor


def wakeups() -> Wakeups:
    loaded = load_wakeups()
    assert loaded is not None, "this machine (x86-64/AArch64 Linux, Jazzy rcl) has the symbol"
    return loaded


def cdr_only(callback: Any) -> Any:
    """A message callback (``cdr, published_ns, sequence``) that passes *callback* the CDR
    only."""
    def served(cdr: bytes, published_ns: int = 0, sequence: int = 0, /) -> None:
        callback(cdr)

    return served


def raw_subscription(node: Node, topic: str, callback: Any) -> Any:
    """A loop-served subscription whose *callback* gets the CDR only."""
    from std_msgs.msg import String

    return node.create_subscription(String, topic, LoopServed(cdr_only(callback)), QOS,
                                    raw=True)


async def publish_until(pub: Any, text: str, done: Any, timeout_s: float = 10.0) -> None:
    """Publish until ``done()`` (discovery takes a moment), yielding to the loop between."""
    from std_msgs.msg import String

    def attempt() -> bool:
        pub.publish(String(data=text))
        return bool(done())

    await wait_until(attempt, timeout_s)


async def test_messages_are_taken_on_the_loop_thread(nodes: Nodes) -> None:
    loop = asyncio.get_running_loop()
    intake = LoopIntake(loop, wakeups())
    got: list[tuple[bytes, int]] = []
    sub = raw_subscription(nodes.node, "/in", lambda cdr: got.append((cdr, threading.get_ident())))
    intake.attach(sub)
    await publish_until(nodes.publisher("/in"), "hello", lambda: got)
    cdr, thread = got[0]
    assert isinstance(cdr, bytes) and b"hello" in cdr
    assert thread == threading.get_ident()  # the loop's thread: no executor involved
    assert intake.taken == len(got)
    intake.close()


async def test_each_message_comes_with_its_publish_time(nodes: Nodes) -> None:
    """The middleware's source timestamp (wall clock ns), which rclpy's executor does
    not pass on: the link judges a message after an outage by it."""
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[tuple[bytes, int]] = []
    sub = nodes.node.create_subscription(
        String, "/stamped", LoopServed(lambda cdr, ns=0, seq=0: got.append((cdr, ns))), QOS,
        raw=True)
    intake.attach(sub)
    pub = nodes.publisher("/stamped")
    await publish_until(pub, "probe", lambda: got)
    before = len(got)
    before_publish = time.time_ns()
    pub.publish(String(data="timed"))
    after_publish = time.time_ns()
    await wait_until(lambda: len(got) > before, 10.0)
    cdr, published_ns = got[-1]
    assert b"timed" in cdr
    assert before_publish <= published_ns <= after_publish
    intake.close()


async def test_a_burst_beyond_one_round_is_taken_whole(nodes: Nodes) -> None:
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[bytes] = []
    intake.attach(raw_subscription(nodes.node, "/burst", got.append))
    pub = nodes.publisher("/burst")
    await publish_until(pub, "probe", lambda: got)
    before = len(got)
    count = 3 * intake_module.MAX_TAKES_PER_ROUND
    for i in range(count):  # no await: all of them wait in the reader when the loop looks
        pub.publish(String(data=f"m{i}"))
    await wait_until(lambda: len(got) >= before + count, 10.0)
    tail = [cdr for cdr in got[before:] if b"probe" not in cdr]
    assert [bytes(f"m{i}", "ascii") in cdr for i, cdr in enumerate(tail)] == [True] * count
    intake.close()


async def test_the_executor_leaves_loop_served_subscriptions_alone(nodes: Nodes) -> None:
    from std_msgs.msg import String

    served: list[bytes] = []
    plain: list[str] = []
    raw_subscription(nodes.node, "/shared", served.append)  # not attached: nobody takes it
    nodes.node.create_subscription(String, "/shared", lambda m: plain.append(m.data), QOS)
    with executor_spinning(nodes):
        await publish_until(nodes.publisher("/shared"), "x", lambda: len(plain) >= 3)
    assert served == []


async def test_detach_stops_taking_and_closes_the_eventfd(nodes: Nodes) -> None:
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[bytes] = []
    sub = raw_subscription(nodes.node, "/detach", got.append)
    intake.attach(sub)
    pub = nodes.publisher("/detach")
    await publish_until(pub, "a", lambda: got)
    fd = intake._served[id(sub)].fd
    intake.detach(sub)
    assert intake._served == {}
    with pytest.raises(OSError):
        os.fstat(fd)  # closed on the loop at once (detach ran on the loop's thread)
    taken = intake.taken
    pub.publish(String(data="late"))
    # The message is still there for whoever takes next: the intake did not.
    assert await _take_within(sub, 5.0) is not None
    assert intake.taken == taken
    intake.close()


async def _take_within(sub: Any, timeout_s: float) -> Any:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while True:
        with sub.handle:
            taken = sub.handle.take_message(sub.msg_type, True)
        if taken is not None:
            return taken
        assert asyncio.get_running_loop().time() < deadline, "nothing to take"
        await asyncio.sleep(0.01)  # polling interval of a deadline-bounded wait


async def test_a_failing_callback_is_counted_and_the_intake_goes_on(
        nodes: Nodes, caplog: pytest.LogCaptureFixture) -> None:
    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[bytes] = []

    def callback(cdr: bytes) -> None:
        if b"bad" in cdr:
            raise ValueError("boom")
        got.append(cdr)

    intake.attach(raw_subscription(nodes.node, "/fail", callback))
    pub = nodes.publisher("/fail")
    with caplog.at_level(logging.ERROR, logger="fleetctl.client.ros.intake"):
        await publish_until(pub, "bad", lambda: intake.failed_callbacks)
    await publish_until(pub, "good", lambda: got)
    assert "boom" in caplog.text
    intake.close()


async def test_attach_needs_a_loop_served_callback(nodes: Nodes) -> None:
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    sub = nodes.node.create_subscription(String, "/plain", lambda m: None, QOS, raw=True)
    with pytest.raises(ValueError, match="LoopServed"):
        intake.attach(sub)


async def test_adaptive_subscription_follows_a_qos_switch_on_the_loop(nodes: Nodes) -> None:
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[bytes] = []
    entry = AdaptiveSubscription(nodes.node, String, "/switch", cdr_only(got.append), no_drop=True,
                                 intake=intake)
    assert entry.loop_served and entry.reliable
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    pub = nodes.publisher("/switch", best_effort)

    def switched() -> bool:
        entry.refresh()  # as the node's timer does, once the publisher is discovered
        return not entry.reliable

    await wait_until(switched, 10.0)
    assert entry.switches == 1 and len(intake._served) == 1
    await publish_until(pub, "after", lambda: got)
    intake.close()


async def test_adaptive_subscription_falls_back_to_the_executor(
        nodes: Nodes, caplog: pytest.LogCaptureFixture) -> None:
    from std_msgs.msg import String

    refusing = Wakeups(set_callback=lambda *_args: 1, eventfd_write=0)  # RCL_RET_ERROR
    intake = LoopIntake(asyncio.get_running_loop(), refusing)
    got: list[bytes] = []
    with caplog.at_level(logging.WARNING, logger="fleetctl.client.ros.qos"):
        entry = AdaptiveSubscription(nodes.node, String, "/fallback", cdr_only(got.append),
                                     no_drop=False, intake=intake)
    assert not entry.loop_served
    assert "taken by the executor thread" in caplog.text
    subs = list(nodes.node.subscriptions)
    assert len(subs) == 1 and not isinstance(subs[0].callback, LoopServed)
    with executor_spinning(nodes):
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        await publish_until(nodes.publisher("/fallback", best_effort), "y", lambda: got)


async def test_the_executor_does_not_spin_beside_a_loop_served_topic(nodes: Nodes) -> None:
    # rclpy's default QoS event handlers of a subscription the executor does not take from
    # kept its wait returning at once on Fast DDS (~900 rounds/s): loop-served
    # subscriptions are created without them.
    from std_msgs.msg import String

    intake = LoopIntake(asyncio.get_running_loop(), wakeups())
    got: list[bytes] = []
    entry = AdaptiveSubscription(nodes.node, String, "/quiet", cdr_only(got.append), no_drop=False,
                                 intake=intake)
    assert entry._subscription.event_handlers == []
    with executor_spinning(nodes) as executor:
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        await publish_until(nodes.publisher("/quiet", best_effort), "z", lambda: len(got) >= 20)
    # One wait of up to 1 s (WAIT_TIMEOUT_NS) at a time, woken by nothing while 20+
    # messages went past on the loop; a spinning executor did thousands.
    assert executor.rounds < 10
    intake.close()


async def test_a_publisher_of_another_type_is_warned_about(
        nodes: Nodes, caplog: pytest.LogCaptureFixture) -> None:
    from std_msgs.msg import Int32, String

    entry = AdaptiveSubscription(nodes.node, String, "/typed_in", cdr_only([].append),
                                 no_drop=False)
    # Another participant (a DDS participant allows one type per topic), as another
    # process would be.
    other = Context()
    rclpy.init(context=other, domain_id=DOMAIN_ID)
    stranger = Node("intake_stranger", context=other)
    try:
        stranger.create_publisher(Int32, "/typed_in", 10)
        def warned() -> bool:
            entry.refresh()  # as the node's timer does, once the publisher is discovered
            return "std_msgs/msg/Int32" in caplog.text

        with caplog.at_level(logging.WARNING, logger="fleetctl.client.ros.qos"):
            await wait_until(warned, 10.0)
            entry.refresh()
    finally:
        stranger.destroy_node()
        other.try_shutdown()
    assert caplog.text.count("a publisher sends std_msgs/msg/Int32") == 1  # once, not per refresh


class RecordingSender:
    """Records the intake's calls to the link around its takes."""

    def __init__(self, log: list[str]) -> None:
        self.log = log

    def hold_wakes(self) -> None:
        self.log.append("hold")

    def send_held(self) -> None:
        self.log.append("send")


async def test_a_sender_is_held_around_each_take_even_when_a_callback_fails(
        nodes: Nodes) -> None:
    from std_msgs.msg import String

    calls: list[str] = []
    intake = LoopIntake(asyncio.get_running_loop(), wakeups(), RecordingSender(calls))

    def callback(cdr: bytes) -> None:
        calls.append("bad" if b"bad" in cdr else "msg")
        if b"bad" in cdr:
            raise ValueError("boom")

    intake.attach(raw_subscription(nodes.node, "/held", callback))
    pub = nodes.publisher("/held")
    await publish_until(pub, "first", lambda: "msg" in calls)
    pub.publish(String(data="bad"))
    await wait_until(lambda: "bad" in calls and calls[-1] == "send", 5.0)
    # Every take is hold ... send, with the messages (and the failing one) inside.
    rounds = "".join({"hold": "(", "send": ")", "msg": "m", "bad": "b"}[c] for c in calls)
    assert rounds.replace("(", "").replace(")", "").count("b") == 1
    depth = 0
    for ch in rounds:
        depth += {"(": 1, ")": -1}.get(ch, 0)
        assert 0 <= depth <= 1
        if ch in "mb":
            assert depth == 1, rounds
    assert depth == 0
    intake.close()
