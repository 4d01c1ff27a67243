"""A robot that deflates its uplink, through a real relay (fleetctl.linkdeflate)."""

from __future__ import annotations

from websockets.asyncio.client import ClientConnection, connect

from fleetctl.batched_connection import BatchedWritesConnection
from fleetctl.linkdeflate import DEFAULT_MAX_MESSAGE_BYTES, RobotDeflateFactory, SmallMessageDeflate
from fleetctl.server.app import RelayServer
from tests.server.conftest import ALICE_TOKEN, client, next_binary, subscribe
from tests.support import string_frame


class BatchedClient(BatchedWritesConnection, ClientConnection):
    """The client side, as the robot link composes it."""


async def test_robot_to_relay_negotiates_inbound_only_and_frames_arrive_unchanged(
        server: RelayServer) -> None:
    # The robot (127.0.0.2 is husky1) offers the extension; alice (a viewer that does not)
    # gets exactly the frames the robot encoded, small and large.
    # no_drop, so that the relay delivers every one (latest-only would keep the last).
    frames_out = [string_frame("/husky1/chat", f"msg {i} " * 20, no_drop=True, seq=i)
                  for i in range(20)]
    frames_out.append(string_frame("/husky1/chat", "x" * (DEFAULT_MAX_MESSAGE_BYTES + 1),
                                   no_drop=True, seq=20))
    async with client(server, token=ALICE_TOKEN) as alice, \
            connect(f"ws://127.0.0.1:{server.port}/", local_addr=("127.0.0.2", 0),
                    compression=None, extensions=[RobotDeflateFactory()], max_size=None,
                    create_connection=BatchedClient) as robot:
        assert isinstance(robot, BatchedClient)
        assert [type(e) for e in robot.protocol.extensions] == [SmallMessageDeflate]
        assert alice.protocol.extensions == []
        assert (await subscribe(alice, "/husky1/.*"))["type"] == "subscribed"
        await robot.send_frames(frames_out)
        got = [await next_binary(alice) for _ in frames_out]
    assert got == frames_out
