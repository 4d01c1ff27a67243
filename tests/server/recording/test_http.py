"""``GET /recordings`` and ``/recordings/<name>``: who sees which file, ranges, and the
``fleetctl recordings --server`` client against a real server."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from fleetctl.cli.recordings import Remote, fetch_remote, list_remote
from fleetctl.errors import FleetError
from fleetctl.server.app import RelayServer
from fleetctl.server.config import WebConfig
from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from fleetctl.server.recording.http import MAX_RANGE_BYTES
from fleetctl.server.recording.mcapfile import McapFile
from fleetctl.server.recording.recorder import Recorder
from fleetctl.wire import samples
from fleetctl.wire.codec import default_codec
from tests.server.certs import self_signed
from tests.server.conftest import ALICE_TOKEN, BOB_TOKEN, client, wait_for
from tests.support import string_frame

# Generous: every server starts a worker process, slow on a loaded machine.
DEADLINE_S = 30.0
IMAGE = "sensor_msgs/msg/CompressedImage"


async def send_chat(srv: RelayServer, robot: Any, n: int) -> Recorder:
    """*n* chat lines from *robot* on /husky1/chat, once the recorder has them all."""
    recorder = srv.recorder
    assert recorder is not None
    for i in range(n):
        await robot.send(string_frame("/husky1/chat", f"one {i}", seq=i + 1))
    await wait_for(lambda: recorder.snapshot()["messages"] == n, DEADLINE_S)
    return recorder


async def test_listing_and_fetching_follow_the_receive_rules(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    config = RecordingConfig(tmp_path / "rec", (RecordingRule(".*"),), flush_interval_s=0.05)
    async with make_server(recording=config) as srv, \
            client(srv, source="127.0.0.2") as husky1, \
            client(srv, source="127.0.0.3") as husky2:
        recorder = await send_chat(srv, husky1, 20)
        await wait_for(lambda: recorder.current_topics == ["/husky1/chat"], DEADLINE_S)
        url = srv.url
        operator, alice, bob = (Remote(url), Remote(url, ALICE_TOKEN),
                                Remote(url, BOB_TOKEN))
        # Bob may receive /husky1/.*: he sees the file while it holds only that topic.
        [seen] = await asyncio.to_thread(list_remote, bob)
        assert (seen.complete, seen.topics) == (False, ["/husky1/chat"])
        await husky2.send(string_frame("/husky2/chat", "two", seq=1))
        await wait_for(lambda: recorder.current_topics == ["/husky1/chat", "/husky2/chat"],
                       DEADLINE_S)
        assert await asyncio.to_thread(list_remote, bob) == []  # now it holds husky2's data
        assert [r.name for r in await asyncio.to_thread(list_remote, operator)] == [seen.name]
        with pytest.raises(FleetError, match="404"):
            await asyncio.to_thread(fetch_remote, bob, seen.name, tmp_path)
        with pytest.raises(FleetError, match="401"):
            await asyncio.to_thread(list_remote, Remote(url, "not-a-token"))
        # Alice (receive .*) fetches the open file: a complete copy of what was flushed.
        await wait_for(lambda: len(list(files.read_messages(tmp_path / "rec" / seen.name)))
                       == 21, DEADLINE_S)
        fetched = await asyncio.to_thread(fetch_remote, alice, seen.name, tmp_path)
        assert fetched.messages == 21 and files.is_complete(fetched.target)
        with pytest.raises(FleetError, match="416"):
            await asyncio.to_thread(alice.get, f"/recordings/{seen.name}", "bytes=999999999-")
    # Closed now: fetched again, byte for byte (the server closed it with its summary).
    async with make_server(recording=config) as srv:
        out = tmp_path / "again.mcap"
        fetched = await asyncio.to_thread(fetch_remote, Remote(srv.url, ALICE_TOKEN),
                                          seen.name, out)
        assert out.read_bytes() == (tmp_path / "rec" / seen.name).read_bytes()
        with out.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 21


async def test_large_files_come_in_ranges(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    directory = tmp_path / "rec"
    directory.mkdir()
    blob = directory / "fleet_big.mcap"
    registry = default_codec().registry
    big = McapFile(blob, registry, 1 << 20)
    for i in range(9):  # 9 MiB of random (incompressible) image data: three ranges
        image = samples.compressed_image(registry, 1 << 20, seed=i)
        big.write("/husky1/image", IMAGE, bytes(registry.typestore.serialize_cdr(image, IMAGE)),
                  1_700_000_000_000_000_000 + i, i + 1)
    big.close()
    config = RecordingConfig(directory, (RecordingRule(".*"),))
    async with make_server(recording=config) as srv:
        remote = Remote(srv.url)
        status, headers, body = await asyncio.to_thread(remote.get,
                                                        "/recordings/fleet_big.mcap")
        assert status == 206 and len(body) == MAX_RANGE_BYTES
        assert headers["Content-Range"] == (f"bytes 0-{MAX_RANGE_BYTES - 1}/"
                                            f"{blob.stat().st_size}")
        status, headers, body = await asyncio.to_thread(
            remote.get, "/recordings/fleet_big.mcap", "bytes=10-19")
        assert body == blob.read_bytes()[10:20]
        fetched = await asyncio.to_thread(fetch_remote, remote, "fleet_big.mcap", tmp_path)
        assert fetched.messages == 9 and fetched.target.read_bytes() == blob.read_bytes()
        for bad in ("/recordings/../auth.yaml", "/recordings/x.txt", "/recordings/nope.mcap"):
            with pytest.raises(FleetError, match="404"):
                await asyncio.to_thread(remote.get, bad)
        # Ranges that cannot be served are 416, not a 500 from int() or a negative read.
        for bad_range in ("bytes=5-2", f"bytes={'9' * 5000}-", f"bytes=0-{'9' * 5000}"):
            with pytest.raises(FleetError, match="416"):
                await asyncio.to_thread(remote.get, "/recordings/fleet_big.mcap", bad_range)


async def test_a_server_without_recording_says_so(
        make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv:
        with pytest.raises(FleetError, match="records nothing"):
            await asyncio.to_thread(list_remote, Remote(srv.url))


async def test_the_web_listener_serves_recordings_to_token_holders(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    # `fleetctl up` publishes only the HTTPS port: people list and fetch there, with a
    # token; no loopback privilege on it (a reverse proxy on the host is loopback too).
    config = RecordingConfig(tmp_path / "rec", (RecordingRule(".*"),), flush_interval_s=0.05)
    cert, key = self_signed(tmp_path / "tls")
    web = WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0)
    async with make_server(recording=config, web=web) as srv, \
            client(srv, source="127.0.0.2") as husky1:
        await send_chat(srv, husky1, 5)
        url = f"https://127.0.0.1:{srv.web_port}"
        [seen] = await asyncio.to_thread(list_remote, Remote(url, BOB_TOKEN, cert))
        assert seen.topics == ["/husky1/chat"]
        await wait_for(lambda: len(list(files.read_messages(tmp_path / "rec" / seen.name)))
                       == 5, DEADLINE_S)
        fetched = await asyncio.to_thread(fetch_remote, Remote(url, ALICE_TOKEN, cert),
                                          seen.name, tmp_path)
        assert fetched.messages == 5
        with pytest.raises(FleetError, match=r"401.*needs a Bearer token.*--token-file"):
            await asyncio.to_thread(list_remote, Remote(url, None, cert))
        # Plain http:// to the TLS port: the server hangs up; it said "cannot reach it".
        for plain in (f"http://127.0.0.1:{srv.web_port}", f"ws://127.0.0.1:{srv.web_port}"):
            with pytest.raises(FleetError, match=r"closed the connection without an answer "
                               r"\(a TLS port\? use https:// or wss://\)"):
                await asyncio.to_thread(list_remote, Remote(plain, ALICE_TOKEN, cert))
        with pytest.raises(FleetError, match=r"401.*matches no user"):
            await asyncio.to_thread(list_remote, Remote(url, "not-a-token", cert))
        with pytest.raises(FleetError, match=r"not trusted.*--ca-file"):
            await asyncio.to_thread(list_remote, Remote(url, ALICE_TOKEN))
