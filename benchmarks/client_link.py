"""Robot client link figures, side by side in one run (issue 3, section 4).

Usage (root, for the network namespaces of part b)::

    .venv/bin/python benchmarks/client_link.py [--seconds 10] [--json out.json]
        [--skip throughput,priority,cpu,dropout,peer,slow,speedup] [--peer-rate 12mbit]

(a) throughput: unshaped loopback, N x 64 KB no_drop frames from the robot into the
    fleetctl relay, from the first send until the pong that acknowledges the last frame;
    RobotLink (adaptive window, fragments) vs a plain websockets client sending the same
    frames back to back to the same relay and then one ping. Bar: >= 90 %.
(b) priority: 1 KB @ 50 Hz (priority 10) alone and with a competing 64 KB @ 6.7 Hz flow
    (priority 1) over a 6 Mbit tbf link between two network namespaces created here
    (relay + consumer in one, robot in the other); RobotLink vs a Robofleet-like
    baseline (n_T = 1, whole messages). Latency = consumer receive - robot publish (one
    host clock). Bar: p99 < 15 ms for RobotLink with the competing flow.
(c) client cost: 10 Hz 1 MB PointCloud2, per message CDR -> rosbags message -> FlatBuffer
    -> RobotLink (the ROS node's per-message path without rclpy's receive), CPU time of
    the robot process over the run. Bar: < 3 % of one core.
(d) dropout: the robot's egress between the namespaces is cut silently for 5 s (bfifo
    limit 0: no netem here); time from restore until latency is back under 2x its
    pre-cut median, and whether every no_drop message arrived in order.
(e) issue 19's load: a pose at 20 Hz and a 720-beam scan at 10 Hz (the e2e load's
    messages; ``--peer-payload string``: frames of about their sizes holding one letter, as
    before 2026-12-07, which the robot deflates to ~2 % and so deflates all, with zlib)
    over a 12 Mbit tbf link (16 KB bucket, as the e2e router), RobotLink against the same
    frames written at once on a plain websockets connection: what the scheduler adds to
    the latency floor on a link that is far from full.
(f) a link slower than the topic: a 150 KB droppable message at 5 Hz over a 3 Mbit tbf
    link (0.4 s of link time each, two periods): messages received per second, their
    latency, the bytes the robot's interface sent per message (what fragment headers
    and messages abandoned mid-send cost) and the robot's CPU; an image of random bytes
    and a cloud of float points, each with the slow-link deflate of every message and
    without it, alternating. The bound is the link: 3 Mbit/s / 150 KB = 2.5 messages/s.
(g) a link that gets faster: issue 19's load (the e2e load's scan and pose) over a 1 Mbit/s
    tbf link with a one-packet bucket, where the robot deflates every message, changed to
    12 Mbit/s with a 16 KB bucket once it does: how long the robot keeps that state, and
    the latency before and after.

Each side runs in its own process: relay + consumer (``client_bench_peer.py``) and robot
(``client_bench_sender.py``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
PY = sys.executable
ROBOT_TOKEN = "bench-robot-token"
CONSUMER_TOKEN = "bench-consumer-token"
NS_ADDR_SERVER = "10.210.0.1"  # inside namespaces this script creates, nowhere else
NS_ADDR_ROBOT = "10.210.0.2"


def write_auth(directory: Path) -> Path:
    def sha(token: str) -> str:
        return hashlib.sha256(token.encode()).hexdigest()

    path = directory / "auth.yaml"
    path.write_text(json.dumps({"version": 1, "identities": [
        {"name": "bench", "token_sha256": sha(ROBOT_TOKEN),
         "rules": [{"topic": "/bench/.*", "op": "send"}]},
        {"name": "consumer", "token_sha256": sha(CONSUMER_TOKEN),
         "rules": [{"topic": ".*", "op": "receive"}]},
    ]}))
    return path


class Peer:
    """The relay + consumer process; ``cmd`` sends one stdin command, reads one JSON line."""

    def __init__(self, prefix: list[str], host: str, auth: Path, *extra: str) -> None:
        self.proc = subprocess.Popen(
            [*prefix, PY, str(HERE / "client_bench_peer.py"), "--host", host, "--auth",
             str(auth), *extra], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(HERE.parent)})
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit("relay process failed to start")
        self.url = f"ws://{host}:{json.loads(line)['port']}/"

    def cmd(self, command: str) -> Any:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def wait_frames(self, topic: str, n: int, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            report = self.cmd("report")
            got = report.get(topic, {})
            if got.get("frames", 0) >= n or time.monotonic() > deadline:
                return dict(got)
            time.sleep(0.05)  # polling another process's counter, with a deadline

    def close(self) -> None:
        try:
            self.cmd("quit")
            self.proc.wait(5)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


def sender(prefix: list[str], *args: str) -> dict[str, Any]:
    out = subprocess.run([*prefix, PY, str(HERE / "client_bench_sender.py"), *args],
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": str(HERE.parent)})
    if out.returncode != 0:
        raise SystemExit(f"sender {args} failed:\n{out.stderr[-2000:]}")
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q / 100 * len(ordered)))]


# -- (a) throughput --------------------------------------------------------------------


def bench_throughput(auth: Path, frames: int, size: int, rounds: int) -> dict[str, Any]:
    peer = Peer([], "127.0.0.1", auth)
    results: dict[str, list[float]] = {"raw": [], "link": [], "link_16k": []}
    cpu_per_gb: dict[str, list[float]] = {"raw": [], "link": [], "link_16k": []}
    modes = {"raw": ["--mode", "raw"],
             "link": ["--mode", "link", "--fragment-bytes", str(1 << 20)],
             "link_16k": ["--mode", "link", "--fragment-bytes", "16384"]}
    try:
        for _ in range(rounds):  # alternate to spread machine noise over all
            for mode, mode_args in modes.items():
                peer.cmd("reset")
                sent = sender([], "throughput", "--url", peer.url, *mode_args,
                              "--frames", str(frames), "--size", str(size))
                results[mode].append(sent["bytes"] / sent["seconds"] / 1e6)
                cpu_per_gb[mode].append(sent["cpu_s"] / (sent["bytes"] / 1e9))
    finally:
        peer.close()
    # Each round runs the three back to back, so the ratio within a round is the least
    # affected by the machine's varying load; report the median of those ratios.
    def ratio(mode: str) -> float:
        return statistics.median(m / r for m, r in zip(results[mode], results["raw"],
                                                       strict=True))

    return {"frames": frames, "frame_bytes": size,
            "raw_MBps": statistics.median(results["raw"]),
            "link_MBps": statistics.median(results["link"]), "fraction": ratio("link"),
            "link_16k_MBps": statistics.median(results["link_16k"]),
            "fraction_16k": ratio("link_16k"), "runs": results,
            "sender_cpu_s_per_GB": {k: statistics.median(v) for k, v in cpu_per_gb.items()}}


# -- (b) priority over a shaped link -----------------------------------------------------


def sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True)


class Namespaces:
    """Two network namespaces joined by a veth pair, the robot side shaped with tbf."""

    def __init__(self, rate: str, burst: str = "32kbit") -> None:
        tag = str(os.getpid())[-6:]
        self.server, self.robot = f"fcs{tag}", f"fcr{tag}"
        self.veth_s, self.veth_r = f"fcvs{tag}", f"fcvr{tag}"
        self.rate, self.burst = rate, burst

    def __enter__(self) -> Namespaces:
        try:
            sh("ip", "netns", "add", self.server)
            sh("ip", "netns", "add", self.robot)
            sh("ip", "link", "add", self.veth_s, "type", "veth", "peer", "name", self.veth_r)
            sh("ip", "link", "set", self.veth_s, "netns", self.server)
            sh("ip", "link", "set", self.veth_r, "netns", self.robot)
            for ns, dev, addr in ((self.server, self.veth_s, NS_ADDR_SERVER),
                                  (self.robot, self.veth_r, NS_ADDR_ROBOT)):
                sh("ip", "-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
                sh("ip", "-n", ns, "link", "set", dev, "up")
                sh("ip", "-n", ns, "link", "set", "lo", "up")
            sh("tc", "-n", self.robot, "qdisc", "replace", "dev", self.veth_r, "root", "tbf",
               "rate", self.rate, "burst", self.burst, "latency", "400ms")
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for ns in (self.server, self.robot):  # deleting a namespace deletes its veth end
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)

    def prefix(self, ns: str) -> list[str]:
        return ["ip", "netns", "exec", ns]


def bench_priority(auth: Path, seconds: float, rate: str, burst: str) -> dict[str, Any]:
    out: dict[str, Any] = {"rate": rate, "burst": burst}
    with Namespaces(rate, burst) as ns:
        peer = Peer(ns.prefix(ns.server), NS_ADDR_SERVER, auth)
        try:
            for label, mode, frag in (("RobotLink, max_fragment_bytes 16 KiB", "link", 16384),
                                      ("RobotLink, max_fragment_bytes 1 MiB", "link", 1 << 20),
                                      ("Robofleet-like (n_T=1, whole)", "baseline", 16384)):
                for cloud in (False, True):
                    peer.cmd("reset")
                    args = ["priority", "--url", peer.url, "--mode", mode, "--seconds",
                            str(seconds), "--fragment-bytes", str(frag)]
                    sent = sender(ns.prefix(ns.robot), *args, *(["--cloud"] if cloud else []))
                    report = peer.cmd("report")
                    out[f"{label} | {'with' if cloud else 'without'} 64 KB flow"] = summarize(
                        report, sent)
        finally:
            peer.close()
    return out


def summarize(report: dict[str, Any], sent: dict[str, Any]) -> dict[str, Any]:
    urgent = report.get("/bench/urgent", {})
    cloud = report.get("/bench/cloud", {})
    lat = urgent.get("latency_ms", [])
    return {
        "urgent_sent": sent["sent"]["/bench/urgent"], "urgent_received": urgent.get("frames", 0),
        "p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99), "max_ms": max(lat, default=float("nan")),
        "cloud_sent": sent["sent"]["/bench/cloud"], "cloud_received": cloud.get("frames", 0),
        "cloud_p50_ms": pct(cloud.get("latency_ms", []), 50),
        # Whether the robot ended deflating every message (a link under 5 Mbit/s on the
        # wire; 6 Mbit/s lies in the band where it stays as it was), and how often it
        # switched.
        "deflate_all": sent["uplink_deflate"]["all_messages"],
        "deflate_switches": sent["uplink_deflate"]["switches"],
    }


# -- (e) issue 19's load -----------------------------------------------------------------


PEER_TOPICS = ("/bench/pose", "/bench/scan")


def bench_peer(auth: Path, seconds: float, rate: str, burst: str,
               payload: str = "real") -> dict[str, Any]:
    """Issue 19's load (a pose at 20 Hz, a 720-beam scan at 10 Hz; *payload* ``real``:
    the e2e load's messages, ``string``: frames of about their sizes holding one letter)
    over a *rate* tbf link: RobotLink against the same frames written at once on a plain
    websockets connection (what the scheduler costs on an idle link), alternating, two
    rounds each."""
    out: dict[str, Any] = {"rate": rate, "burst": burst, "payload": payload}
    with Namespaces(rate, burst) as ns:
        peer = Peer(ns.prefix(ns.server), NS_ADDR_SERVER, auth)
        try:
            lat: dict[str, dict[str, list[float]]] = {}
            extra: dict[str, Any] = {}
            for _ in range(2):
                for mode in ("link", "raw"):
                    peer.cmd("reset")
                    sent = sender(ns.prefix(ns.robot), "peer", "--url", peer.url, "--mode",
                                  mode, "--seconds", str(seconds), "--warmup", "2",
                                  "--payload", payload)
                    report = peer.cmd("report")
                    for topic in PEER_TOPICS:
                        lat.setdefault(mode, {}).setdefault(topic, []).extend(
                            report.get(topic, {}).get("latency_ms", []))
                    extra[mode] = {k: v for k, v in sent.items() if k != "sent"}
            for mode, topics in lat.items():
                out[mode] = {topic: latency_summary(v) for topic, v in topics.items()}
                out[mode]["link_state"] = extra[mode]
        finally:
            peer.close()
    return out


# -- (f) a link slower than the topic ----------------------------------------------------


SLOW_SIZE, SLOW_PERIOD_S = 150_000, 0.2
SLOW_PAYLOADS = ("image", "cloud")


def bench_slow(auth: Path, seconds: float, rate: str, rounds: int = 2) -> dict[str, Any]:
    """One 150 KB droppable topic at 5 Hz over a *rate* tbf link, for each payload of
    :data:`SLOW_PAYLOADS` *rounds* times with the slow-link deflate and without it,
    alternating; the bytes counted are those the robot's interface sent."""
    out: dict[str, Any] = {"rate": rate, "rounds": []}
    with Namespaces(rate, "32kb") as ns:
        peer = Peer(ns.prefix(ns.server), NS_ADDR_SERVER, auth)
        try:
            for payload in SLOW_PAYLOADS:
                for _ in range(rounds):
                    for deflate in (True, False):
                        peer.cmd("reset")
                        sent = sender(
                            ns.prefix(ns.robot), "slow", "--url", peer.url, "--seconds",
                            str(seconds), "--size", str(SLOW_SIZE), "--period",
                            str(SLOW_PERIOD_S), "--warmup", "3", "--payload", payload,
                            "--count-dev", ns.veth_r,
                            *(() if deflate else ("--no-slow-deflate",)))
                        out["rounds"].append(slow_round(peer, sent, seconds, payload, deflate))
        finally:
            peer.close()
    return out


def slow_round(peer: Peer, sent: dict[str, Any], seconds: float, payload: str,
               deflate: bool) -> dict[str, Any]:
    cloud = peer.cmd("report").get("/bench/cloud", {})
    received, topic = cloud.get("frames", 0), sent["topic"]
    completed = max(topic["sent"], 1)
    return {
        "payload": payload, "slow_deflate": deflate,
        "deflating_all": sent["uplink_deflate"]["all_messages"],
        "offered": sent["sent"]["/bench/cloud"], "received": received,
        "received_per_s": received / seconds,
        "p50_ms": pct(cloud.get("latency_ms", []), 50),
        "frame_bytes": sent["frame_bytes"],
        "sent_MB": topic["sent_bytes"] / 1e6,
        "link_bytes_per_received": topic["sent_bytes"] / max(received, 1),
        "wire_bytes_per_message": sent["wire_bytes"] / completed,
        "wire_over_frame": sent["wire_bytes"] / completed / sent["frame_bytes"],
        "cpu_percent": 100 * sent["cpu_s"] / seconds,
        "superseded": topic["dropped_superseded"],
        "replaced": topic["dropped_replaced"]}


# -- (g) a link that gets faster ---------------------------------------------------------


SPEEDUP_SLOW = ("1mbit", "1600")  # a one-packet bucket: the load's scans queue
SPEEDUP_FAST = ("12mbit", "16kb")  # issue 19's fan-out link, the e2e router's bucket


def bench_speedup(auth: Path, before_s: float, after_s: float) -> dict[str, Any]:
    """Issue 19's load (the e2e load's scan and pose) over a 1 Mbit/s tbf link, where the
    robot deflates every message and cuts scans to fill TCP segments, until the link
    becomes 12 Mbit/s: how long the robot keeps the slow-link state after that, and the
    latency before and after. Why: in some e2e fan-out passes on a 12 Mbit/s link the
    robot took a fresh link for a 2-4 Mbit/s one (one cold first acknowledgement: the rule
    waits for 1 s of slow readings since, fleetctl/client/slowdeflate.py) and deflated
    everything for the whole run (docs/peers.md); were the rule unable to see a faster
    link from its own slow-link traffic, a robot whose Wi-Fi or LTE gets better would
    stay slow too."""
    out: dict[str, Any] = {"slow": SPEEDUP_SLOW, "fast": SPEEDUP_FAST, "rows": []}
    with Namespaces(*SPEEDUP_SLOW) as ns:
        peer = Peer(ns.prefix(ns.server), NS_ADDR_SERVER, auth)
        proc = subprocess.Popen(
            [*ns.prefix(ns.robot), PY, str(HERE / "client_bench_sender.py"), "speedup",
             "--url", peer.url, "--seconds", str(before_s + after_s)],
            stdout=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(HERE.parent)})
        try:
            assert proc.stdout is not None
            switched_at: float | None = None
            for line in proc.stdout:
                row = json.loads(line)
                if "t" not in row:
                    out["sender"] = row
                    continue
                out["rows"].append(row)
                if switched_at is None and row["t"] >= before_s and row["deflate_all"]:
                    rate, burst = SPEEDUP_FAST
                    sh("tc", "-n", ns.robot, "qdisc", "change", "dev", ns.veth_r, "root",
                       "tbf", "rate", rate, "burst", burst, "latency", "400ms")
                    switched_at = row["t"]
                    out["before"] = peer_latencies(peer.cmd("report"))
                    peer.cmd("reset")
            if proc.wait() != 0:
                raise SystemExit("the speedup sender failed")
            out["after"] = peer_latencies(peer.cmd("report"))
        finally:
            if proc.poll() is None:  # stopped early (an error above): not left running
                proc.kill()
                proc.wait()
            peer.close()
    rows = out["rows"]
    out["on_at_s"] = next((r["t"] for r in rows if r["deflate_all"]), None)
    out["switched_at_s"] = switched_at
    out["off_after_s"] = None if switched_at is None else next(
        (r["t"] - switched_at for r in rows if r["t"] > switched_at and not r["deflate_all"]),
        None)
    return out


def peer_latencies(report: dict[str, Any]) -> dict[str, dict[str, float]]:
    """:func:`latency_summary` per topic of :data:`PEER_TOPICS` in a consumer report."""
    return {topic: latency_summary(report.get(topic, {}).get("latency_ms", []))
            for topic in PEER_TOPICS}


def latency_summary(latencies_ms: list[float]) -> dict[str, float]:
    """Count, p50 and p99 (ms) of one topic's latencies."""
    return {"n": len(latencies_ms), "p50_ms": pct(latencies_ms, 50),
            "p99_ms": pct(latencies_ms, 99)}


def peer_cells(row: dict[str, Any]) -> str:
    """Part (e)'s and (g)'s figures of each topic of :data:`PEER_TOPICS` in *row*, on one
    line."""
    return "  ".join(f"{t.rsplit('/', 1)[1]} {row[t]['p50_ms']:6.2f} / {row[t]['p99_ms']:6.2f} "
                     f"ms (n {row[t]['n']})" for t in PEER_TOPICS if t in row)


# -- (d) dropout ------------------------------------------------------------------------


def bench_dropout(auth: Path, cut_s: float, rate: str) -> dict[str, Any]:
    """Cut the robot's egress silently (bfifo limit 0) for *cut_s*, then restore it."""
    with Namespaces(rate) as ns:
        peer = Peer(ns.prefix(ns.server), NS_ADDR_SERVER, auth)
        try:
            peer.cmd("reset")
            before_s, after_s = 4.0, 6.0
            proc = subprocess.Popen(
                [*ns.prefix(ns.robot), PY, str(HERE / "client_bench_sender.py"), "priority",
                 "--url", peer.url, "--events", "--seconds", str(before_s + cut_s + after_s)],
                stdout=subprocess.PIPE, text=True, env={**os.environ,
                                                        "PYTHONPATH": str(HERE.parent)})
            with proc:  # an interrupted run must not leave the sender behind
                try:
                    time.sleep(1.0 + before_s)  # the scenario's timeline (warm-up, steady)
                    cut_ns = time.time_ns()
                    sh("tc", "-n", ns.robot, "qdisc", "replace", "dev", ns.veth_r, "root",
                       "bfifo", "limit", "0")
                    time.sleep(cut_s)
                    sh("tc", "-n", ns.robot, "qdisc", "replace", "dev", ns.veth_r, "root",
                       "tbf", "rate", rate, "burst", "32kbit", "latency", "400ms")
                    restore_ns = time.time_ns()
                    out, _ = proc.communicate(timeout=120)
                except BaseException:
                    proc.kill()
                    raise
            sent = json.loads(out.strip().splitlines()[-1])
            report = peer.cmd("report")
        finally:
            peer.close()
    urgent, events = report.get("/bench/urgent", {}), report.get("/bench/events", {})
    lat, recv = urgent.get("latency_ms", []), urgent.get("recv_ns", [])
    pre = [v for v, r in zip(lat, recv, strict=True) if r < cut_ns]
    median = statistics.median(pre) if pre else float("nan")
    back = [r for v, r in zip(lat, recv, strict=True) if r > restore_ns and v < 2 * median]
    first_any = [r for r in recv if r > restore_ns]
    return {
        "cut_s": cut_s, "pre_median_ms": median,
        "first_frame_after_restore_s": (first_any[0] - restore_ns) / 1e9 if first_any else None,
        "latency_back_under_2x_median_s": (back[0] - restore_ns) / 1e9 if back else None,
        "events_sent": sent["sent"]["/bench/events"], "events_received": events.get("frames"),
        "events_duplicates": events.get("duplicates"), "events_gaps": events.get("gaps"),
        "events_reorders": events.get("reorders"), "reconnects": sent["reconnects"],
        "link_timeouts": sent["link_timeouts"],
    }


# -- (c) client cost -----------------------------------------------------------------------


def bench_cpu(auth: Path, seconds: float, fragment_bytes: int) -> dict[str, Any]:
    # --light: the relay's process must not be slowed by reassembling 1 MB clouds.
    peer = Peer([], "127.0.0.1", auth, "--light")
    try:
        result = sender([], "cpu", "--url", peer.url, "--seconds", str(seconds),
                        "--fragment-bytes", str(fragment_bytes))
        result["received"] = peer.cmd("report").get("/bench/points", {}).get("frames", 0)
    finally:
        peer.close()
    return result


# -- main ---------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--rate", default="6mbit")
    # tc tbf bucket of the shaped link; the e2e router uses 16 KB (its floor for GSO), and
    # a deep bucket is what tempts a delay-based window into overshooting after idle.
    parser.add_argument("--burst", default="32kbit")
    parser.add_argument("--skip", default="")
    parser.add_argument("--peer-rate", default="12mbit",
                        help="tbf rate of part (e), issue 19's fan-out link")
    parser.add_argument("--peer-payload", choices=["real", "string"], default="real",
                        help="part (e)'s messages: the e2e load's (real) or one repeated "
                             "letter (string, the figures before 2026-12-07)")
    parser.add_argument("--slow-rate", default="3mbit",
                        help="tbf rate of part (f), a link slower than its topic")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    # The relay, senders and network namespaces are cleaned up by context managers and
    # finally blocks; on SIGTERM too, unwind through them instead of dying in place.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    skip = set(args.skip.split(",")) - {""}
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        auth = write_auth(Path(tmp))
        if "throughput" not in skip:
            results["throughput"] = t = bench_throughput(auth, args.frames, 65536, args.rounds)
            print(f"(a) throughput, unshaped loopback, {t['frames']} x 64 KB no_drop frames; "
                  f"medians of {args.rounds} rounds (fraction: median of per-round ratios)")
            print(f"    plain websockets                     {t['raw_MBps']:8.1f} MB/s")
            print(f"    RobotLink, max_fragment_bytes 1 MiB  {t['link_MBps']:8.1f} MB/s  = "
                  f"{t['fraction']:.1%} (bar >= 90%)")
            print(f"    RobotLink, max_fragment_bytes 16 KiB {t['link_16k_MBps']:8.1f} MB/s  = "
                  f"{t['fraction_16k']:.1%}")
            cpu = t["sender_cpu_s_per_GB"]
            print(f"    sender CPU s per GB: plain {cpu['raw']:.2f}, RobotLink 1 MiB "
                  f"{cpu['link']:.2f}, 16 KiB {cpu['link_16k']:.2f}")
        if "priority" not in skip:
            if os.geteuid() != 0 or shutil.which("ip") is None:
                raise SystemExit("part (b) needs root and iproute2 (ip netns, tc)")
            results["priority"] = p = bench_priority(auth, args.seconds, args.rate, args.burst)
            print(f"(b) 1 KB @ 50 Hz latency over {p['rate']} tbf, burst {p['burst']} "
                  f"({args.seconds:.0f} s each)")
            print(f"    {'sender | competing flow':58s} {'p50':>7s} {'p99':>7s} {'max':>7s}"
                  f"  urgent rx/tx  cloud rx/tx")
            for key, row in p.items():
                if key in ("rate", "burst"):
                    continue
                print(f"    {key:58s} {row['p50_ms']:6.1f}ms {row['p99_ms']:6.1f}ms "
                      f"{row['max_ms']:6.1f}ms  {row['urgent_received']:5d}/"
                      f"{row['urgent_sent']:<5d}  {row['cloud_received']:4d}/{row['cloud_sent']}"
                      f"  deflate all {'on' if row['deflate_all'] else 'off'}"
                      f" ({row['deflate_switches']} switches)")
        if "cpu" not in skip:
            print("(c) 10 Hz PointCloud2 of 1 MB, per message CDR -> rosbags -> FlatBuffer -> "
                  "RobotLink, robot process CPU over the run (bar < 3% of one core)")
            results["cpu"] = {}
            for cap in (1 << 20, 16384):
                results["cpu"][cap] = c = bench_cpu(auth, args.seconds, cap)
                print(f"    max_fragment_bytes {cap:>7d}: CPU {c['cpu_percent']:.2f}%, "
                      f"RSS {c['rss_mb']:.0f} MB, sent {c['sent']}/{c['offered']}, "
                      f"received {c['received']}")
        if "dropout" not in skip:
            results["dropout"] = d = bench_dropout(auth, 5.0, args.rate)
            print(f"(d) dropout: robot egress silently cut for {d['cut_s']:.0f} s "
                  f"(bfifo limit 0), {args.rate} tbf otherwise; 1 KB @ 50 Hz droppable + "
                  f"10 Hz no_drop")
            print(f"    first frame {d['first_frame_after_restore_s']} s after restore; latency "
                  f"back under 2x pre-cut median ({d['pre_median_ms']:.1f} ms) after "
                  f"{d['latency_back_under_2x_median_s']} s; reconnects {d['reconnects']} "
                  f"(link timeouts {d['link_timeouts']})")
            print(f"    no_drop: {d['events_received']}/{d['events_sent']} received, "
                  f"gaps {d['events_gaps']}, reorders {d['events_reorders']}, "
                  f"duplicates {d['events_duplicates']}")
        if "peer" not in skip:
            results["peer"] = e = bench_peer(auth, args.seconds, args.peer_rate, "16kb",
                                             args.peer_payload)
            print(f"(e) issue 19's load (pose @ 20 Hz, 720-beam scan @ 10 Hz, droppable, "
                  f"{e['payload']} payloads) over {e['rate']} tbf, burst {e['burst']}; p50 / "
                  "p99 ms, two rounds each")
            for mode, label in (("link", "RobotLink"), ("raw", "plain websockets, at once")):
                print(f"    {label:26s} {peer_cells(e[mode])}")
            print(f"    RobotLink state at the end: {e['link']['link_state']}")
        if "slow" not in skip:
            results["slow"] = f = bench_slow(auth, args.seconds, args.slow_rate)
            print(f"(f) 150 KB droppable @ 5 Hz over {f['rate']} tbf (slower than the "
                  f"topic); bound: the link's rate / 150 KB; wire: bytes the robot's "
                  f"interface sent per message sent (IP, TCP, WebSocket included)")
            for row in f["rounds"]:
                mode = "deflate all" if row["deflating_all"] else "small only "
                print(f"    {row['payload']:5s} {mode} received {row['received']}/"
                      f"{row['offered']} ({row['received_per_s']:.2f}/s), p50 "
                      f"{row['p50_ms']:.0f} ms, wire {row['wire_bytes_per_message']:,.0f} B "
                      f"per {row['frame_bytes']:,} B message "
                      f"({row['wire_over_frame']:.3f}x), robot CPU "
                      f"{row['cpu_percent']:.1f} %, superseded {row['superseded']}")
        if "speedup" not in skip:
            results["speedup"] = g = bench_speedup(auth, 5.0, args.seconds)
            print(f"(g) issue 19's load over a {g['slow'][0]} tbf link (bucket {g['slow'][1]} "
                  f"B) that becomes {g['fast'][0]} (bucket {g['fast'][1]}) once the robot "
                  "deflates every message")
            def secs(x: float | None) -> str:
                return "never" if x is None else f"{x:.2f}"

            print(f"    deflating every message from {secs(g['on_at_s'])} s; link changed at "
                  f"{secs(g['switched_at_s'])} s; back to small messages only "
                  f"{secs(g['off_after_s'])} s later (reported every 0.25 s; switches "
                  f"{g.get('sender', {}).get('switches')})")
            for phase in ("before", "after"):
                print(f"    {phase:6s} {peer_cells(g.get(phase, {}))}")
            last = g["rows"][-1] if g["rows"] else {}
            print(f"    at the end: link rate {last.get('link_rate_Bps', 0) * 8e-6:.1f} Mbit/s "
                  f"of frame bytes, fragments {last.get('fragment_bytes')} B, window "
                  f"{last.get('window_bytes')} B")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
