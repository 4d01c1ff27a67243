"""``fleetctl client``: the robot client process (rclpy node + WebSocket link).

Threads: the asyncio loop with :class:`~fleetctl.client.transport.RobotLink` runs in the main
thread, and so do the uncompressed ``publish`` topics' subscriptions where the middleware can
wake the loop itself (:mod:`fleetctl.client.ros.intake`): their messages are taken, encoded
and queued without a thread hop. The rclpy executor spins in a worker thread for the rest
(timers, the battery topic, QoS events, compressed topics, and every ``publish`` topic where
the intake is unavailable); its
frames cross to the loop with ``RobotLink.offer_threadsafe``, and frames go from the loop to
ROS with ``Bridge.deliver`` (rclpy publishers are thread-safe).

Shutdown on SIGINT/SIGTERM: the link unsubscribes and closes, the intake lets go of its
subscriptions, then the executor stops and the node is destroyed (which removes its
subscriptions), then rclpy shuts down.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions

from fleetctl.client.config import ClientConfig, PublishSpec
from fleetctl.client.ros.bridge import Bridge, LinkPort
from fleetctl.client.ros.executor import NodeExecutor
from fleetctl.client.ros.intake import LoopIntake, load_wakeups
from fleetctl.client.transport import RobotLink
from fleetctl.gilswitch import tune_gil
from fleetctl.wire.codec import Codec
from fleetctl.wire.control import UNKNOWN_BATTERY, encode_status
from fleetctl.wire.registry import TypeRegistry

log = logging.getLogger(__name__)

STATUS_PRIORITY = 8.0  # small and what the fleet view shows first: ahead of sensor data
_EXECUTOR_JOIN_S = 5.0


def build_registry() -> TypeRegistry:
    """The default registry plus every message type the installed ROS packages define."""
    registry = TypeRegistry.default()
    try:
        registry.from_rclpy()
    except Exception as exc:  # an odd installed .msg must not stop a robot using others
        log.warning("could not load message definitions from installed ROS packages: %s", exc)
    return registry


def status_encoder(codec: Codec, robot_name: str,
                   location: str = "") -> Callable[[float | None], bytes]:
    """``encode(battery) -> frame`` of this robot's RobofleetStatus (design.md section 1).

    The battery is a fraction in [0, 1], or None (sent as -1: unknown); *location* is
    client.yaml's ``status.location``. Each frame gets the next sequence number, starting
    at the wall clock in microseconds.
    """
    seq = itertools.count(time.time_ns() // 1000)

    def encode(battery: float | None) -> bytes:
        return encode_status(
            robot_name, status="OK", is_ok=True,
            battery_level=UNKNOWN_BATTERY if battery is None else battery,
            location=location, publish_time_ns=time.time_ns(), seq=next(seq), codec=codec,
        )

    return encode


def _port(link: RobotLink, status_topic: str) -> LinkPort:
    def offer(topic: str, frame: bytes, priority: float, no_drop: bool,
              keyframe: bool = False, published_ns: int = 0) -> None:
        try:
            link.offer_threadsafe(topic, frame, priority=priority, no_drop=no_drop,
                                  keyframe=keyframe, published_ns=published_ns)
        except RuntimeError:
            # The loop is gone (shutting down): a callback raced the executor's shutdown.
            log.debug("dropped a frame on %s: the link is stopping", topic)

    def send(spec: PublishSpec, frame: bytes, published_ns: int) -> None:
        offer(spec.remote_topic, frame, spec.priority, spec.no_drop,
              published_ns=published_ns)

    def send_status(frame: bytes) -> None:
        offer(status_topic, frame, STATUS_PRIORITY, False)

    def send_video(spec: PublishSpec, frame: bytes, keyframe: bool) -> None:
        offer(spec.remote_topic, frame, spec.priority, spec.no_drop, keyframe)

    return LinkPort(admit=link.admit, send=send, send_status=send_status,
                    connects=lambda: link.connects, send_video=send_video,
                    feedback=link.feedback)


def _spin(executor: NodeExecutor, loop: asyncio.AbstractEventLoop,
          stop: asyncio.Event) -> None:
    """Spin until shutdown; if spinning fails, log it and stop the client (never stall)."""
    try:
        executor.spin()
    except Exception:
        log.exception("the rclpy executor failed; stopping the client")
        loop.call_soon_threadsafe(stop.set)


async def _serve(config: ClientConfig, context: Context) -> dict[str, Any]:
    """Run node and link until a signal; return the link's final stats."""
    codec = Codec(build_registry())
    bridge: Bridge | None = None

    def on_frame(frame: bytes) -> None:
        if bridge is not None:
            bridge.deliver(frame)

    link = RobotLink(config, on_frame=on_frame)
    loop = asyncio.get_running_loop()
    wakeups = load_wakeups()
    intake = None if wakeups is None else LoopIntake(loop, wakeups, link)
    bridge = Bridge(config, codec, codec.registry.typestore, _port(link, config.status_topic),
                    status_encoder(codec, config.robot_name, config.status.location),
                    context=context, intake=intake)
    executor = NodeExecutor(bridge, context)
    stop = asyncio.Event()
    spinner = threading.Thread(target=_spin, args=(executor, loop, stop), name="rclpy-executor",
                               daemon=True)
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    # `kill -USR1` (`systemctl kill -s USR1 fleetctl-client`): the counters of a running
    # client, which --print-stats gives only at exit.
    loop.add_signal_handler(signal.SIGUSR1, _log_stats, link, bridge, intake)
    spinner.start()
    runner = asyncio.create_task(link.run())
    log.info("client %s: %d topics out (%d taken on the loop thread), %d in, server %s",
             config.robot_name, len(config.publish),
             sum(entry.loop_served for entry in bridge.inputs), len(config.subscribe),
             config.server_url)
    try:
        await asyncio.wait([runner, asyncio.create_task(stop.wait())],
                           return_when=asyncio.FIRST_COMPLETED)
    finally:
        await link.stop()
        if intake is not None:
            intake.close()
        executor.shutdown()
        spinner.join(_EXECUTOR_JOIN_S)
        bridge.destroy_node()
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1):
            loop.remove_signal_handler(signum)
    failure = runner.exception() if runner.done() and not runner.cancelled() else None
    if failure is not None:
        raise failure
    return _stats(link, bridge, intake)


def _log_stats(link: RobotLink, bridge: Bridge, intake: LoopIntake | None) -> None:
    """One INFO line ``stats: {JSON}`` (the executor's thread may add a topic to a counter
    dict while it is read: then read again)."""
    for _ in range(3):
        try:
            text = json.dumps(_stats(link, bridge, intake), default=str)
        except RuntimeError:  # "dictionary changed size during iteration"
            continue
        log.info("stats: %s", text)
        return


def _stats(link: RobotLink, bridge: Bridge, intake: LoopIntake | None) -> dict[str, Any]:
    """The link's counters with the node's (``bridge``, ``video``, ``intake``)."""
    stats = link.stats()
    stats["bridge"] = vars(bridge.stats)
    stats["video"] = {topic: vars(video.stats) for topic, video in bridge.videos.items()}
    if intake is not None:
        stats["intake"] = {"taken": intake.taken, "failed_callbacks": intake.failed_callbacks}
    return stats


def run_client(config: ClientConfig) -> dict[str, Any]:
    """Run the robot client until SIGINT/SIGTERM; return the final link and node stats.

    Raises:
        ConfigError: a configured message type is not installed.
    """
    tune_gil()
    context = Context()
    # Signals are the asyncio loop's job: rclpy's own handlers would shut the context down
    # under the executor's feet before the link has unsubscribed.
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        return asyncio.run(_serve(config, context))
    finally:
        context.try_shutdown()
