"""Bytes per message on the robot's uplink, per topic, for issue 19's load (no network).

Usage::

    .venv/bin/python benchmarks/uplink_bytes.py [--seconds 60]

The e2e ``peer`` load in publish order (a realistic 720-beam scan at 10 Hz, a pose at
20 Hz: :mod:`fleetctl.e2e.payloads`), each message as:

- **CDR**: what zenoh (and ROS) carries;
- **frame**: today's self-describing fleetctl frame (Robofleet convention), what a peer
  without the uplink deflate sends, and what the relay forwards to every receiver;
- **deflated**: the same frames through the robot's permessage-deflate
  (:class:`fleetctl.linkdeflate.SmallMessageDeflate`, one context for the connection, as
  on the wire), whole and split into the 1 KiB fragments the scheduler used at 4 Mbit/s
  (``fragment_time_s`` 3 ms) until 2026-12-07; the WebSocket header (2-4 bytes + the
  4-byte mask) is included in every figure but CDR's;
- **filled**: what the robot sends since, deflating every message on a link under
  5 Mbit/s: fragments sized to fill whole TCP segments of WireGuard's MSS (1368 bytes)
  once deflated (:class:`fleetctl.client.segmentfill.SegmentFill`, fed by the deflate as
  on the wire).

Also printed: TCP segments per message for the two fragmentings (each costs ~130 bytes
of TCP, IP, UDP and WireGuard headers, which are not in the byte figures: the e2e
``peer`` scenario measures the whole uplink) and the deflate's CPU per message.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from websockets import frames

from fleetctl.client.segmentfill import SegmentFill
from fleetctl.e2e import payloads
from fleetctl.linkdeflate import COMPRESS_SETTINGS, WINDOW_BITS, SmallMessageDeflate
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragmenter import fast_split

LOAD = (("/robot1/scan", "sensor_msgs/msg/LaserScan", 10.0, 5760),
        ("/robot1/pose", "geometry_msgs/msg/PoseStamped", 20.0, 0))
FRAGMENT_BYTES = 1024
WIREGUARD_MSS = 1368  # MTU 1420 less IP (20), TCP (20) and its timestamp option (12)


def _ws_header(size: int) -> int:
    return (2 if size < 126 else 4 if size < 65536 else 10) + 4  # + the client's mask


def _schedule(seconds: float) -> list[tuple[float, str, str, int, int]]:
    """(time, topic, type, size, seq) in publish order."""
    events = []
    for topic, type_name, rate, size in LOAD:
        events += [(i / rate, topic, type_name, size, i) for i in range(int(seconds * rate))]
    return sorted(events)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    codec = default_codec()
    ts = codec.registry.typestore
    whole = SmallMessageDeflate(True, False, 15, WINDOW_BITS, dict(COMPRESS_SETTINGS),
                                max_message_bytes=16 * 1024)
    split = SmallMessageDeflate(True, False, 15, WINDOW_BITS, dict(COMPRESS_SETTINGS),
                                max_message_bytes=16 * 1024)
    filled = SmallMessageDeflate(True, False, 15, WINDOW_BITS, dict(COMPRESS_SETTINGS),
                                 max_message_bytes=16 * 1024)
    filled.deflate_all = True
    fill = SegmentFill()
    filled.fragment_observer = fill
    sums: dict[str, dict[str, float]] = {}
    deflate_s = 0.0
    for t, topic, type_name, size, seq in _schedule(args.seconds):
        msg: Any = payloads.build(ts, type_name, size, seq, int(1.7e18 + t * 1e9))
        cdr = len(ts.serialize_cdr(msg, type_name))
        frame = codec.encode(msg, type_name, topic, seq=seq, publish_time_ns=int(1.7e18 + t * 1e9))
        start = time.perf_counter()
        packed = whole.encode(frames.Frame(frames.OP_BINARY, frame)).data
        deflate_s += time.perf_counter() - start
        pieces = fast_split(frame, topic=topic, message_id=seq, max_fragment_bytes=FRAGMENT_BYTES,
                            no_drop=False)
        split_sizes = [len(p) + _ws_header(len(p)) for p in (
            split.encode(frames.Frame(frames.OP_BINARY, f)).data for f in pieces)]
        # The 4 Mbit/s link's budget (3 ms) holds one segment: whole frames up to two.
        share = fill.payload_bytes(topic, mss=WIREGUARD_MSS, budget_wire_bytes=1500.0,
                                   max_fragment_bytes=1 << 22)
        shares = ([frame] if len(frame) <= 3000 else
                  fast_split(frame, topic=topic, message_id=seq, max_fragment_bytes=FRAGMENT_BYTES,
                             no_drop=False, payload_bytes=share))
        filled_sizes = [len(p) + _ws_header(len(p)) for p in (
            filled.encode(frames.Frame(frames.OP_BINARY, f)).data for f in shares)]
        row = sums.setdefault(topic, dict.fromkeys(
            ("n", "cdr", "frame", "deflated", "split", "filled", "split_segs", "filled_segs"),
            0.0))
        row["n"] += 1
        row["cdr"] += cdr
        row["frame"] += len(frame) + _ws_header(len(frame))
        row["deflated"] += len(packed) + _ws_header(len(packed))
        row["split"] += sum(split_sizes)
        row["filled"] += sum(filled_sizes)
        row["split_segs"] += sum(-(-n // WIREGUARD_MSS) for n in split_sizes)
        row["filled_segs"] += sum(-(-n // WIREGUARD_MSS) for n in filled_sizes)
    print(f"{args.seconds:g} s of the peer load; mean bytes per message (WebSocket header "
          "included except for CDR)")
    print(f"{'topic':<16}{'CDR':>8}{'frame':>8}{'deflated':>10}{'1 KiB frags':>13}"
          f"{'filled':>8}{'vs CDR':>9}{'vs frame':>10}{'segments 1 KiB / filled':>25}")
    total = dict.fromkeys(("cdr", "frame", "deflated", "split", "filled", "split_segs",
                           "filled_segs"), 0.0)
    for topic, row in sums.items():
        n = row["n"]
        mean = {k: row[k] / n for k in total}
        for k in total:
            total[k] += row[k] / args.seconds
        print(f"{topic:<16}{mean['cdr']:>8.0f}{mean['frame']:>8.0f}{mean['deflated']:>10.0f}"
              f"{mean['split']:>13.0f}{mean['filled']:>8.0f}"
              f"{mean['deflated'] / mean['cdr']:>9.3f}{mean['deflated'] / mean['frame']:>10.3f}"
              f"{mean['split_segs']:>14.2f} / {mean['filled_segs']:.2f}")
    print("per second (payload only, KB/s): " + ", ".join(
        f"{k} {v / 1e3:.1f}" for k, v in total.items() if not k.endswith("_segs")))
    print(f"TCP segments per second: 1 KiB fragments {total['split_segs']:.1f}, "
          f"filled {total['filled_segs']:.1f}")
    count = sum(r["n"] for r in sums.values())
    print(f"deflate CPU: {deflate_s / count * 1e6:.1f} us per message "
          f"({deflate_s / args.seconds * 100:.3f} % of a core)")


if __name__ == "__main__":
    main()
