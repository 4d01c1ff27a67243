"""The e2e fleet consumer: WebSocket clients of the server that record every message.

Runs in a container on the server network::

    python -m fleetctl.e2e.consumer --url wss://172.20.0.3:8443/ --ca-file /e2e/tls-cert.pem \\
        --tls-name server --token-file /e2e/token --subscribe '/robot1/.*' --count 4 \\
        --out /e2e/out --name mc4

``wss://`` URLs check the server's certificate against ``--ca-file`` (the fleet's
self-signed one) under the name ``--tls-name`` (default: the URL's host).

Each of ``--count`` connections authenticates with the Bearer token, subscribes, waits for
the server's ``subscribed`` answer, then writes ``NAME-I.ready``. Every binary frame is
reassembled (:class:`~fleetctl.wire.fragments.Reassembler`), decoded
(:class:`~fleetctl.wire.codec.Codec`) and recorded as a :class:`~fleetctl.e2e.samples.Sample`
line in ``NAME-I.jsonl``; the receipt time is taken when the last fragment arrived, before
decoding. Video frames (``foxglove_msgs/msg/CompressedVideo``) are also decoded, as the
web page decodes them (:mod:`fleetctl.e2e.videoview`: refused after a lost reference,
keyframe requests while waiting); their samples say whether and when each was shown.
SIGTERM closes the connections and flushes the files; the exit code is 1 when a
connection failed.

``--session NAME`` names a session (``X-Fleetctl-Session: NAME-I``), and ``--url`` given
more than once is a failover list: such a consumer does not fail when its connection
ends, it reconnects to the next URL (as the robot client does) and resumes its session
there; its duplicate filter and files carry on across connections. Each reconnection is
one ``reconnected`` line on stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import signal
import ssl
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from fleetctl.client.transport import SESSION_HEADER
from fleetctl.client.videobits import is_keyframe
from fleetctl.e2e.payloads import read_stamp
from fleetctl.e2e.samples import Sample, dump
from fleetctl.e2e.videoview import VideoViewer
from fleetctl.errors import FleetError
from fleetctl.frame_sink import FrameSink
from fleetctl.wire.codec import default_codec
from fleetctl.wire.control import encode_keyframe_request, encode_subscription
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import read_metadata

MAX_FRAME_BYTES = 32 * 1024 * 1024
REASSEMBLY_MAX_BYTES = 64 * 1024 * 1024
REASSEMBLY_TIMEOUT_S = 10.0
SUBSCRIBE_TIMEOUT_S = 10.0
# Between the end of a connection and the next attempt (failover consumers).
RECONNECT_PAUSE_S = 0.1


class Recorder:
    """Turns received frames into samples (pure apart from the output file).

    Args:
        name: Consumer name written into each sample.
        out: Where sample lines go.
        viewer: Decodes video frames and writes their samples; None: video frames are
            recorded undecoded.
    """

    VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"

    def __init__(self, name: str, out: TextIO, viewer: VideoViewer | None = None) -> None:
        self.name = name
        self.out = out
        self.viewer = viewer
        self._lock = threading.Lock()  # the viewer writes from its own thread
        self.codec = default_codec()
        self.reassembler = Reassembler(REASSEMBLY_MAX_BYTES, REASSEMBLY_TIMEOUT_S)
        self.errors = 0  # frames that could not be decoded or carried no stamp (logged)
        self.duplicates = 0  # no_drop frames dropped as resends (see feed)
        self._last_no_drop_seq: dict[str, int] = {}

    def feed(self, frame: bytes, recv_time_ns: int) -> Sample | None:
        """Record one binary frame received at *recv_time_ns*; None until a message is whole."""
        try:
            if read_metadata(frame).type == FRAGMENT_TYPE:
                whole = self.reassembler.feed(frame, time.monotonic())
                if whole is None:
                    return None
                frame = whole
            meta, msg = self.codec.decode(frame)
            if meta.no_drop and not self._fresh(meta.topic, meta.seq):
                return None
            stamp = read_stamp(msg)
        except (WireError, FleetError) as exc:
            self.errors += 1
            print(f"e2e consumer {self.name}: dropped a frame: {exc}", file=sys.stderr)
            return None
        sample = Sample(meta.topic, stamp.seq, stamp.publish_time_ns, recv_time_ns,
                        len(frame), self.name)
        if meta.type == self.VIDEO_TYPE:
            data = bytes(msg.data)
            sample = Sample(sample.topic, sample.seq, sample.publish_time_ns,
                            sample.recv_time_ns, sample.size_bytes, sample.consumer,
                            wire_seq=meta.seq, keyframe=is_keyframe(str(msg.format), data))
            if self.viewer is not None:
                self.viewer.offer(sample, str(msg.format), data)
                return sample
        self.write(sample)
        return sample

    def write(self, sample: Sample) -> None:
        """Append *sample* to the output (thread-safe)."""
        with self._lock:
            self.out.write(dump([sample]))


    def _fresh(self, topic: str, seq: int) -> bool:
        # no_drop is at-least-once across reconnects (client transport docstring): a
        # receiver drops a no_drop frame whose sender seq is not above the last one seen.
        last = self._last_no_drop_seq.get(topic)
        if last is not None and seq <= last:
            self.duplicates += 1
            return False
        self._last_no_drop_seq[topic] = seq
        return True


class ConsumerConnection(FrameSink, ClientConnection):
    """The consumer's connection: binary frames are recorded in the read that brought them
    (:mod:`fleetctl.frame_sink`, as fleetctl's client receives), the receipt time taken
    there, as the zenoh consumer takes it in zenoh's callback."""


async def _subscribe(ws: ConsumerConnection, regex: str) -> None:
    await ws.send(encode_subscription(regex))
    while True:
        msg = await ws.recv()
        ws.message_handled()
        if isinstance(msg, str):
            event = json.loads(msg)
            if event.get("type") == "subscribed":
                return
            if event.get("type") == "error":
                raise FleetError(f"server refused the subscription: {event}")


@dataclass(frozen=True)
class Tls:
    """How a ``wss://`` connection checks the server.

    Attributes:
        ca_file: PEM certificate(s) to trust; None: the system's.
        name: The name the certificate must carry; None: the URL's host.
    """

    ca_file: Path | None = None
    name: str | None = None

    def kwargs(self, url: str) -> dict[str, Any]:
        """``connect`` arguments for *url* (none for ``ws://``)."""
        if not url.startswith("wss://"):
            return {}
        context = ssl.create_default_context(
            cafile=str(self.ca_file) if self.ca_file is not None else None)
        return {"ssl": context, **({"server_hostname": self.name} if self.name else {})}


async def consume(urls: list[str], token: str, regex: str, name: str, out_dir: Path,
                  tls: Tls = Tls(), session: str | None = None) -> None:
    """Subscribe to *regex* and record until cancelled: over one connection, or, with a
    session or several URLs, over as many as it takes (the next URL after each end).

    Raises:
        FleetError: the server refused the subscription or did not answer in time.
        OSError, ConnectionClosed: the connection failed (one URL, no session).
    """
    loop = asyncio.get_running_loop()
    headers = {"Authorization": f"Bearer {token}"}
    if session is not None:
        headers[SESSION_HEADER] = session
    failover = len(urls) > 1 or session is not None
    requests = itertools.count(1)
    current: list[ConsumerConnection] = []

    def request(topic: str) -> None:  # from the viewer's thread
        frame = encode_keyframe_request(topic, publish_time_ns=time.time_ns(),
                                        seq=next(requests))
        if current:
            ws = current[-1]
            loop.call_soon_threadsafe(lambda: asyncio.ensure_future(ws.send(frame)))

    with (out_dir / f"{name}.jsonl").open("a", buffering=1) as out:
        recorder = Recorder(name, out)

        def sink(frame: bytes) -> bool:  # in data_received, on the loop thread
            recorder.feed(frame, time.time_ns())
            return True

        recorder.viewer = VideoViewer(recorder.write, request)
        try:
            for attempt in itertools.count():
                url = urls[attempt % len(urls)]
                try:
                    # max_queue=None: frames are read as fast as they come; this process
                    # must not be the bottleneck that delays receipt.
                    async with connect(url, additional_headers=headers,
                                       max_size=MAX_FRAME_BYTES, max_queue=None,
                                       open_timeout=SUBSCRIBE_TIMEOUT_S,
                                       create_connection=ConsumerConnection,
                                       **tls.kwargs(url)) as ws:
                        assert isinstance(ws, ConsumerConnection)
                        current.append(ws)
                        ws.frame_sink = sink
                        await asyncio.wait_for(_subscribe(ws, regex), SUBSCRIBE_TIMEOUT_S)
                        (out_dir / f"{name}.ready").write_text("ok")
                        if attempt:
                            print(f"e2e consumer {name}: reconnected to {url}",
                                  file=sys.stderr)
                        async for frame in ws:  # frames that queued behind a text one
                            if isinstance(frame, bytes):
                                recorder.feed(frame, time.time_ns())
                            ws.message_handled()
                except (OSError, TimeoutError, ConnectionClosed):
                    if not failover:
                        raise
                if not failover:
                    return
                await asyncio.sleep(RECONNECT_PAUSE_S)  # a retry pace, as the client's
        finally:
            await asyncio.to_thread(recorder.viewer.close)


async def run(urls: list[str], token: str, regex: str, name: str, count: int, out_dir: Path,
              tls: Tls = Tls(), session: str | None = None) -> int:
    """Run *count* consumers until SIGTERM/SIGINT; returns the number that failed."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    tasks = [asyncio.create_task(consume(
        urls, token, regex, f"{name}-{i}", out_dir, tls,
        None if session is None else f"{session}-{i}")) for i in range(count)]
    waiter = asyncio.create_task(stop.wait())
    await asyncio.wait([waiter, *tasks], return_when=asyncio.FIRST_COMPLETED)
    failed = 0
    for task in tasks:
        if task.done():
            exc = task.exception()
            failed += 1
            print(f"e2e consumer: a connection ended: {exc!r}", file=sys.stderr)
        else:
            task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    waiter.cancel()
    return failed


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (``python -m fleetctl.e2e.consumer``)."""
    parser = argparse.ArgumentParser(prog="python -m fleetctl.e2e.consumer")
    parser.add_argument("--url", required=True, action="append",
                        help="relay URL; more than once: a failover list")
    parser.add_argument("--session", help="session name (each connection adds -I)")
    parser.add_argument("--ca-file", type=Path, help="PEM certificate to trust (wss://)")
    parser.add_argument("--tls-name", help="name the server's certificate must carry")
    parser.add_argument("--token-file", type=Path, required=True)
    parser.add_argument("--subscribe", default=".*", help="RE2 topic regex")
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--name", default="c")
    parser.add_argument("--out", type=Path, required=True, help="directory for sample files")
    args = parser.parse_args(argv)
    try:
        token = args.token_file.read_text().strip()
    except OSError as exc:
        print(f"e2e consumer: --token-file {args.token_file}: {exc.strerror}", file=sys.stderr)
        return 2
    if args.count < 1:
        print("e2e consumer: --count must be at least 1", file=sys.stderr)
        return 2
    failed = asyncio.run(run(args.url, token, args.subscribe, args.name, args.count, args.out,
                             Tls(args.ca_file, args.tls_name), args.session))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
