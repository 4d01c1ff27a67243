"""The zenoh baseline of the ``peer`` scenario: router, robot-side bridge, consumers.

Eclipse Zenoh 1.x through its Python bindings (``eclipse-zenoh``, in the client image for
this baseline only), three roles in three containers::

    python -m fleetctl.e2e.zenohpeer router --settings best
    python -m fleetctl.e2e.zenohpeer bridge --profile peer --connect tcp/10.8.0.1:7447 \\
        --settings best
    python -m fleetctl.e2e.zenohpeer consumer --profile peer --connect tcp/172.20.0.3:7447 \\
        --count 4 --name zd4 --out /e2e/out

- **router**: a zenoh session in ``router`` mode listening on ``tcp/0.0.0.0:7447``; the
  scenario runs it in the fleetctl server's network namespace (so robots reach it at the
  server's address, through the tunnel when there is one).
- **bridge**: what zenoh-bridge-ros2dds does for each ROS 2 publisher: an rclpy
  subscription (raw CDR, the publisher's reliability) and a zenoh publisher on the key
  ``robot1/<topic>`` putting the CDR bytes as they come (``client`` mode, connected to the
  router).
- **consumer**: ``--count`` zenoh sessions (``client`` mode), each subscribing
  ``robot1/**``, deserializing the CDR with rosbags and writing one
  :class:`~fleetctl.e2e.samples.Sample` line per message, like the WebSocket consumer.

Settings (``--settings``), in every role's session config and the bridge's publishers:

- ``default``: zenoh-bridge-ros2dds's defaults for these topics: the load publishes
  RELIABLE, so the bridge's routes block (congestion control ``BLOCK``,
  ``reliable_routes_blocking: true``), priority ``DATA``, not express; zenoh's default
  transport (2-batch TX queues, OS socket buffers, 10 s lease).
- ``best``: the settings most favourable to fresh data: congestion control ``DROP``,
  express, the pose at ``INTERACTIVE_HIGH`` and every other topic at ``DATA``, one-batch
  TX queues, 8 KiB socket send and receive buffers, a 3 s lease.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from fleetctl.e2e.payloads import read_stamp
from fleetctl.e2e.profiles import ROBOT, Profile, profile
from fleetctl.e2e.samples import Sample, dump
from fleetctl.errors import FleetError

PORT = 7447
SETTINGS = ("default", "best")
HIGH_PRIORITY_TOPICS = ("/pose",)  # the best settings' higher zenoh priority


def key_of(topic: str) -> str:
    """The zenoh key of local ROS topic *topic* (``/pose`` -> ``robot1/pose``)."""
    return f"{ROBOT}{topic}"


def session_config(settings: str, mode: str, *, listen: str | None = None,
                   connect: str | None = None) -> Any:
    """A ``zenoh.Config`` for *mode* (``router`` or ``client``) under *settings*.

    Raises:
        FleetError: unknown settings.
    """
    import zenoh

    if settings not in SETTINGS:
        raise FleetError(f"zenoh settings must be one of {SETTINGS}, got {settings!r}")
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    # No multicast scouting: the roles find each other through the endpoints given.
    config.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        config.insert_json5("listen/endpoints", json.dumps([listen]))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps([connect]))
    if settings == "best":
        queues = {p: 1 for p in ("control", "real_time", "interactive_high",
                                 "interactive_low", "data_high", "data", "data_low",
                                 "background")}
        config.insert_json5("transport/link/tx/queue/size", json.dumps(queues))
        config.insert_json5("transport/link/tx/lease", "3000")
        config.insert_json5("transport/link/tcp/so_sndbuf", "8192")
        config.insert_json5("transport/link/tcp/so_rcvbuf", "8192")
    return config


def publisher_options(settings: str, topic: str) -> dict[str, Any]:
    """``declare_publisher`` keyword arguments for *topic* under *settings*."""
    import zenoh

    if settings == "default":
        return {"congestion_control": zenoh.CongestionControl.BLOCK,
                "priority": zenoh.Priority.DATA, "express": False}
    priority = (zenoh.Priority.INTERACTIVE_HIGH if topic in HIGH_PRIORITY_TOPICS
                else zenoh.Priority.DATA)
    return {"congestion_control": zenoh.CongestionControl.DROP, "priority": priority,
            "express": True}


def _wait_for_signal() -> None:
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass


def run_router(settings: str, listen: str) -> None:
    """A zenoh router until SIGTERM/SIGINT."""
    import zenoh

    with zenoh.open(session_config(settings, "router", listen=listen)):
        print(f"zenoh router: listening on {listen} ({settings} settings)", flush=True)
        _wait_for_signal()


def run_bridge(p: Profile, settings: str, connect: str) -> None:
    """Route each of *p*'s ROS 2 topics to zenoh until SIGTERM/SIGINT."""
    import zenoh
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from fleetctl.client.ros.msgtypes import message_class
    from fleetctl.client.ros.spin import spin_until_signal

    with zenoh.open(session_config(settings, "client", connect=connect)) as session:

        def setup(node: Any) -> None:
            for load in p.topics:
                pub = session.declare_publisher(key_of(load.topic),
                                                **publisher_options(settings, load.topic))
                # The bridge's reader matches the publisher's QoS (RELIABLE here).
                qos = QoSProfile(  # type: ignore[no-untyped-call]  # rclpy has no hints
                    history=HistoryPolicy.KEEP_LAST, depth=10,
                    reliability=ReliabilityPolicy.RELIABLE)
                node.create_subscription(message_class(load.type), load.topic,
                                         lambda cdr, pub=pub: pub.put(bytes(cdr)), qos,
                                         raw=True)
            print(f"zenoh bridge: {[t.topic for t in p.topics]} -> {connect} "
                  f"({settings} settings)", flush=True)

        spin_until_signal("e2e_zenoh_bridge", setup)


def run_consumers(p: Profile, settings: str, connect: str, name: str, count: int,
                  out_dir: Path) -> None:
    """*count* zenoh subscribers of ``robot1/**`` recording samples until SIGTERM."""
    import zenoh

    from fleetctl.wire.registry import TypeRegistry

    ts = TypeRegistry.default().typestore
    types = {key_of(t.topic): (t.type, t.remote_topic) for t in p.topics}
    sessions, files = [], []
    try:
        for i in range(count):
            label = f"{name}-{i}"
            out = (out_dir / f"{label}.jsonl").open("a", buffering=1)
            files.append(out)
            lock = threading.Lock()

            def on_sample(sample: Any, out: Any = out, label: str = label,
                          lock: threading.Lock = lock) -> None:
                now = time.time_ns()
                entry = types.get(str(sample.key_expr))
                if entry is None:
                    return
                cdr = sample.payload.to_bytes()
                try:
                    stamp = read_stamp(ts.deserialize_cdr(cdr, entry[0]))
                except (FleetError, ValueError) as exc:
                    print(f"zenoh consumer {label}: bad sample: {exc}", file=sys.stderr)
                    return
                with lock:
                    out.write(dump([Sample(entry[1], stamp.seq, stamp.publish_time_ns, now,
                                           len(cdr), label)]))

            session = zenoh.open(session_config(settings, "client", connect=connect))
            sessions.append(session)
            session.declare_subscriber(f"{ROBOT}/**", on_sample)
            (out_dir / f"{label}.ready").write_text("ok")
        _wait_for_signal()
    finally:
        for session in sessions:
            session.close()  # type: ignore[no-untyped-call]  # zenoh ships no hints
        for out in files:
            out.close()


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (``python -m fleetctl.e2e.zenohpeer``)."""
    parser = argparse.ArgumentParser(prog="python -m fleetctl.e2e.zenohpeer")
    parser.add_argument("role", choices=("router", "bridge", "consumer"))
    parser.add_argument("--settings", choices=SETTINGS, default="default")
    parser.add_argument("--listen", default=f"tcp/0.0.0.0:{PORT}")
    parser.add_argument("--connect", help="the router's endpoint (tcp/HOST:PORT)")
    parser.add_argument("--profile", default="peer")
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--name", default="z")
    parser.add_argument("--out", type=Path, help="directory for sample files")
    args = parser.parse_args(argv)
    try:
        if args.role == "router":
            run_router(args.settings, args.listen)
            return 0
        if not args.connect:
            parser.error(f"{args.role} needs --connect tcp/HOST:PORT")
        p = profile(args.profile)
        if args.role == "bridge":
            run_bridge(p, args.settings, args.connect)
        else:
            if args.out is None or args.count < 1:
                parser.error("consumer needs --out and --count >= 1")
            run_consumers(p, args.settings, args.connect, args.name, args.count, args.out)
    except FleetError as exc:
        print(f"zenoh {args.role}: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
