"""HeldPongs on a real websockets server protocol: a pong waits for its frames' store."""

from __future__ import annotations

import asyncio

from websockets.frames import Frame, Opcode
from websockets.protocol import Protocol, Side, State

from fleetctl.server.cluster.storeacks import StoreAcks
from fleetctl.server.heldpongs import MAX_HELD_PONGS, HeldPongs
from tests.support import wait_until


class Connection:
    """What HeldPongs uses of a websockets connection: its protocol and send_data."""

    def __init__(self) -> None:
        # The server side of an open connection (after the opening handshake).
        self.protocol = Protocol(Side.SERVER, state=State.OPEN)
        self.out = b""
        self.pongs_held: HeldPongs | None = None

    def send_data(self) -> None:
        self.out += b"".join(self.protocol.data_to_send())

    def ping(self, data: bytes) -> None:
        """A client's ping arrives (masked, as clients send)."""
        self.protocol.receive_data(Frame(Opcode.PING, data).serialize(mask=True,
                                                                         extensions=[]))
        self.send_data()  # as Connection.data_received does after parsing
        if self.pongs_held is not None:
            self.pongs_held.settle()  # as RelayConnection.data_received does after that

    def pongs(self) -> list[bytes]:
        """Payloads of the pongs written so far (server frames are unmasked)."""
        found, out = [], self.out
        while out:
            assert out[0] == 0x8A, out  # FIN + PONG
            size = out[1]
            found.append(out[2:2 + size])
            out = out[2 + size:]
        return found


def held(connection: Connection, acks: StoreAcks, marks: list[int],
         hold_max_s: float = 10.0) -> HeldPongs:
    connection.pongs_held = HeldPongs(connection, acks, lambda: marks[-1], hold_max_s)
    return connection.pongs_held


async def test_a_pong_goes_at_once_when_its_frames_are_stored() -> None:
    connection, acks = Connection(), StoreAcks()
    held(connection, acks, [0])
    connection.ping(b"p1")
    assert connection.pongs() == [b"p1"] and acks.held == 0


async def test_a_pong_waits_for_its_frames_and_later_pongs_wait_behind_it() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    pongs = held(connection, acks, marks)
    marks.append(acks.note_offered())  # frame 1 sent, then a ping
    connection.ping(b"p1")
    marks.append(acks.note_offered())  # frame 2, ping, then a ping with no frame before
    connection.ping(b"p2")
    connection.ping(b"p3")
    assert connection.pongs() == [] and pongs.waiting == 3 and acks.held == 3
    acks.note_done()
    assert connection.pongs() == [b"p1"]
    acks.note_done()
    assert connection.pongs() == [b"p1", b"p2", b"p3"] and pongs.waiting == 0
    connection.ping(b"p4")
    assert connection.pongs()[-1] == b"p4"


async def test_a_pong_goes_after_the_bound_even_unstored() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    held(connection, acks, marks, hold_max_s=0.05)
    marks.append(acks.note_offered())
    connection.ping(b"p1")
    assert connection.pongs() == []
    await wait_until(lambda: connection.pongs() == [b"p1"], 5.0)
    assert acks.unstored == 1
    acks.note_done()  # the store comes later: nothing is sent twice
    assert connection.pongs() == [b"p1"]


async def test_the_stream_away_releases_held_pongs() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    held(connection, acks, marks)
    marks.append(acks.note_offered())
    connection.ping(b"p1")
    acks.set_bypass(True)
    assert connection.pongs() == [b"p1"] and acks.unstored == 0


async def test_held_pongs_are_bounded_and_the_last_acknowledges_the_rest() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    pongs = held(connection, acks, marks)
    marks.append(acks.note_offered())
    for i in range(MAX_HELD_PONGS + 10):
        connection.ping(b"p%d" % i)
    assert pongs.waiting == MAX_HELD_PONGS and acks.coalesced == 10
    acks.note_done()
    assert connection.pongs() == [b"p%d" % i for i in range(10, MAX_HELD_PONGS + 10)]


async def test_a_closing_connection_drops_its_held_pongs() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    pongs = held(connection, acks, marks)
    marks.append(acks.note_offered())
    connection.ping(b"p1")
    connection.protocol.state = State.CLOSING
    acks.note_done()
    assert connection.pongs() == [] and pongs.waiting == 0


async def test_other_frames_pass_untouched() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    held(connection, acks, marks)
    marks.append(acks.note_offered())
    connection.ping(b"p1")  # held
    connection.protocol.send_ping(b"server ping")
    connection.send_data()
    assert connection.out == Frame(Opcode.PING, b"server ping").serialize(
        mask=False, extensions=[])
    await asyncio.sleep(0)  # nothing scheduled releases it
    assert connection.out.count(b"p1") == 0


async def test_a_ping_read_with_a_frame_waits_for_that_frame() -> None:
    connection, acks, marks = Connection(), StoreAcks(), [0]
    held(connection, acks, marks)
    # websockets answers the ping while parsing, before the frame read with it is handled.
    connection.protocol.receive_data(Frame(Opcode.PING, b"p1").serialize(mask=True,
                                                                         extensions=[]))
    connection.send_data()
    marks.append(acks.note_offered())  # the frame is handled after the parse
    assert connection.pongs_held is not None
    connection.pongs_held.settle()
    assert connection.pongs() == [] and acks.held == 1
    acks.note_done()
    assert connection.pongs() == [b"p1"]


async def test_a_pong_whose_frames_are_not_handled_yet_never_expires() -> None:
    """The bound is for the store, not for frames the relay has not taken: a pong queued
    while its frames are held over a rate (RelayConnection.decline: no settle yet) must
    not go when the timer armed for an earlier pong finds it past the bound. Before, the
    timer sent it unsettled, and a client forgot the held no_drop frames on it."""
    connection, acks, marks = Connection(), StoreAcks(), [0]
    held(connection, acks, marks, hold_max_s=0.05)
    marks.append(acks.note_offered())
    connection.ping(b"p1")  # settled, waits for its store: the timer is armed
    connection.protocol.receive_data(Frame(Opcode.PING, b"p2").serialize(mask=True,
                                                                         extensions=[]))
    connection.send_data()  # p2 read with frames the relay holds: not settled
    await wait_until(lambda: connection.pongs() == [b"p1"], 5.0)  # p1 past the bound
    deadline = asyncio.get_running_loop().time() + 0.3  # p2's bound, and then some
    while asyncio.get_running_loop().time() < deadline:
        assert connection.pongs() == [b"p1"]
        await asyncio.sleep(0.01)
    assert connection.pongs_held is not None
    connection.pongs_held.settle()  # its frames taken: now it may wait for the store
    await wait_until(lambda: connection.pongs() == [b"p1", b"p2"], 5.0)
