"""In a cluster too, no pong after frames the relay discarded (real nats-server, a real
replica, a hand-written client): the pong of a robot's ping waits in HeldPongs for its
no_drop frames' store and then goes through the connection's pong gate, which a close
shuts (RelayConnection.discard_from_now). Without it, a token revoked while the robot's
frames were in flight had its ping answered after those frames were discarded, as on
one process (tests/server/test_pongs_after_discard.py)."""

from __future__ import annotations

import asyncio
import copy
from collections.abc import Callable

from fleetctl.server.app import RelayServer
from tests.server.cluster.conftest import stream_takes_stores
from tests.server.cluster.natsproc import NatsServer
from tests.server.conftest import AUTH, auth_map
from tests.server.test_pongs_after_discard import (
    PING,
    arrived,
    events,
    frame,
    opened,
    pongs_and_close,
    pongs_until,
    relay_side,
    taken,
)


async def test_frames_after_a_revocation_get_no_pong_from_a_replica(
    nats_server: NatsServer, make_replica: Callable[..., RelayServer],
) -> None:
    async with make_replica("relay-a", [nats_server.url]) as srv:
        await stream_takes_stores(srv)
        raw = await opened(srv, b"X-Fleetctl-Session: s1\r\n")
        raw.writer.write(events(1, 3) + frame(PING, b"before"))
        assert await pongs_until(raw, b"before") and taken(srv) == 3
        [relay] = relay_side(srv, "alice")
        assert relay.held_pongs is not None  # the cluster's pong path
        late = events(4, 8) + frame(PING, b"after")
        raw.writer.write(late)
        arrived(relay, len(late))
        without_alice = copy.deepcopy(AUTH)
        without_alice["identities"] = [i for i in AUTH["identities"] if i["name"] != "alice"]
        srv.core.reload_auth(auth_map(without_alice))  # what an auth.yaml reload applies
        pongs, code = await asyncio.wait_for(pongs_and_close(raw), 10)
        assert code == 4403
        assert taken(srv) == 3
        assert b"after" not in pongs
        raw.close()
