"""In a cluster too, frames over a rate wait and the pong comes after them (real
nats-server, a real replica, a hand-written client): the pong waits in HeldPongs, which
settles it only once the held frames were taken, and its 250 ms bound (for the store)
does not send it before (tests/server/test_pongs_after_rate_limits.py for one process)."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from fleetctl.server import relay
from fleetctl.server.app import RelayServer
from tests.server.cluster.conftest import stream_takes_stores
from tests.server.cluster.natsproc import NatsServer
from tests.server.test_pongs_after_discard import BINARY, PING, events, frame, opened, relay_side
from tests.server.test_pongs_after_rate_limits import pong_and_texts
from tests.support import string_frame


async def test_frames_on_new_topics_over_the_rate_wait_on_a_replica(
    nats_server: NatsServer, make_replica: Callable[..., RelayServer],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """40 no_drop frames on new topics past a burst of 20 at 20/s (a second of waiting,
    four times the pong's store bound), then 2 more and a ping: the pong comes once all
    were taken."""
    monkeypatch.setattr(relay, "NEW_TOPICS_BURST", 20)
    monkeypatch.setattr(relay, "NEW_TOPICS_PER_S", 20.0)
    async with make_replica("relay-a", [nats_server.url]) as srv:
        await stream_takes_stores(srv)
        raw = await opened(srv, b"X-Fleetctl-Session: s1\r\n")
        [connection] = relay_side(srv, "alice")
        assert connection.held_pongs is not None  # the cluster's pong path
        frames = b"".join(frame(BINARY, string_frame(f"/husky1/t{n}", f"{n}", no_drop=True))
                          for n in range(40))
        raw.writer.write(frames + events(1, 2) + frame(PING, b"after"))
        await pong_and_texts(raw, b"after", srv, 2)
        assert sum(srv.metrics.messages_in.get(f"/husky1/t{n}", 0) for n in range(40)) == 40
        raw.close()
