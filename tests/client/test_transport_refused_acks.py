"""A pong on a connection the server refused is no acknowledgement (found by
benchmarks/soak_client.py: no_drop events lost while the relay refused the robot's token).

The link sends its frames, then a ping, the moment the upgrade returns. A relay that
refuses the token (4401), or past its failed-login budget (4429), drops those frames, but
its WebSocket protocol still answers the ping, and under load that pong can leave before
the close: the link took it as proof that the frames were delivered, forgot them, and the
soak's consumer never got them (15-170 events per 20 s of refusal). A fleetctl relay
(``X-Fleetctl-Standby: 1`` on its upgrade response) welcomes every connection it accepts,
so on such a connection a pong counts only once the welcome came.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from websockets.asyncio.server import ServerConnection, serve
from websockets.http11 import Request, Response

from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.standby import STANDBY_HEADER
from fleetctl.client.transport import RobotLink
from fleetctl.wire.metadata import read_metadata
from tests.client.conftest import robot_config, running, wait_until
from tests.support import decode_text, string_frame

FAST = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=0.6, open_timeout_s=1.0)
QUICK_RETRIES = {"reconnect_min_s": 0.01, "reconnect_max_s": 0.02,
                 "standby_connection": False}
EVENTS = "/r1/events"


def as_fleetctl_relay(connection: ServerConnection, request: Request,
                      response: Response) -> Response:
    """What the fleetctl relay says on every upgrade it answers (it takes standbys)."""
    del connection, request
    response.headers[STANDBY_HEADER] = "1"
    return response


def offer_events(link: RobotLink, count: int) -> None:
    for n in range(1, count + 1):
        link.offer(EVENTS, string_frame(EVENTS, f"e{n}", no_drop=True, seq=n), priority=1.0,
                   no_drop=True)


async def test_frames_a_refusing_server_ponged_are_sent_again(tmp_path: Path) -> None:
    """First connection: the server reads the robot's frames (its protocol answers the
    ping that follows them), then refuses the token, as the relay does when it gets to
    it late. Second: it welcomes the robot. Every event must arrive there."""
    connections = 0
    welcomed: list[str] = []

    async def handler(ws: ServerConnection) -> None:
        nonlocal connections
        connections += 1
        if connections == 1:
            for _ in range(3):  # the events; the ping after them is answered meanwhile
                await ws.recv()
            await ws.send(json.dumps({"type": "error", "code": "bad_token",
                                      "message": "unknown token"}))
            await ws.close(4401, "bad token")
            return
        await ws.send(json.dumps({"type": "welcome", "identities": ["r1"]}))
        async for message in ws:
            if isinstance(message, bytes) and read_metadata(message).topic == EVENTS:
                welcomed.append(decode_text(message))

    async with serve(handler, "127.0.0.1", 0, process_response=as_fleetctl_relay) as server:
        port = server.sockets[0].getsockname()[1]
        cfg = robot_config(f"ws://127.0.0.1:{port}/", tmp_path, limits=QUICK_RETRIES)
        link = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
        offer_events(link, 3)  # queued before the first connection, sent the moment it opens
        async with running(link):
            await wait_until(lambda: len(welcomed) >= 3)
            stats = link.stats()
    assert welcomed == ["e1", "e2", "e3"]
    assert stats["connects"] == 2 and stats["server_errors"] == {"bad_token": 1}
    assert stats["topics"][EVENTS]["requeued"] == 3


async def test_a_server_that_never_welcomes_still_acknowledges(tmp_path: Path) -> None:
    """A Robofleet-convention server (no fleetctl headers, no welcome): its pongs are the
    only acknowledgements there are, and they still count."""
    got: list[str] = []

    async def handler(ws: ServerConnection) -> None:
        async for message in ws:
            if isinstance(message, bytes) and read_metadata(message).topic == EVENTS:
                got.append(decode_text(message))

    async with serve(handler, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        cfg = robot_config(f"ws://127.0.0.1:{port}/", tmp_path, limits=QUICK_RETRIES)
        link = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
        offer_events(link, 3)
        async with running(link):
            await wait_until(lambda: link.stats()["topics"].get(EVENTS, {}).get("acked") == 3)
            stats = link.stats()
    assert got == ["e1", "e2", "e3"]
    assert stats["no_drop_unacked"] == 0 and stats["connects"] == 1


async def test_pongs_before_the_welcome_count_once_it_comes(tmp_path: Path) -> None:
    """A relay may answer the robot's first ping before its welcome goes out (the pong is
    its protocol's, the welcome its handler's): the acknowledgement waits for the welcome,
    it is not lost."""
    release = asyncio.Event()

    async def handler(ws: ServerConnection) -> None:
        for _ in range(3):
            await ws.recv()
        await release.wait()
        await ws.send(json.dumps({"type": "welcome", "identities": ["r1"]}))
        await ws.wait_closed()

    async with serve(handler, "127.0.0.1", 0, process_response=as_fleetctl_relay) as server:
        port = server.sockets[0].getsockname()[1]
        cfg = robot_config(f"ws://127.0.0.1:{port}/", tmp_path, limits=QUICK_RETRIES)
        link = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
        offer_events(link, 3)
        try:
            async with running(link):
                await wait_until(lambda: link.stats()["topics"].get(EVENTS, {}).get("sent") == 3)
                await wait_until(lambda: not link._pings)  # the ping after them was answered
                acked_before_welcome = link.stats()["topics"][EVENTS]["acked"]
                release.set()
                await wait_until(lambda: link.stats()["topics"][EVENTS]["acked"] == 3)
                stats = link.stats()
        finally:
            release.set()  # the server's handler ends, whatever failed
    assert acked_before_welcome == 0
    assert stats["connects"] == 1 and stats["no_drop_unacked"] == 0
