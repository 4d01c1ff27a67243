"""The topic catalog: channels appear with their first sender, go with their last one,
and fragmented or compressed topics get their real type."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fleetctl.server.foxglove.catalog import MAX_CHANNELS, TopicCatalog
from fleetctl.server.foxglove.messages import Channel
from fleetctl.wire import fragments
from fleetctl.wire.codec import default_codec
from fleetctl.wire.compression import CompressionCodec, compress
from fleetctl.wire.metadata import read_metadata
from tests.server.foxglove.conftest import SCAN_TYPE, scan_frame
from tests.support import string_frame


@dataclass
class Sender:
    peer_id: int


def catalog() -> tuple[TopicCatalog, list[tuple[str, bool]]]:
    heard: list[tuple[str, bool]] = []
    cat = TopicCatalog(default_codec(), 1 << 24)

    def listen(channel: Channel, added: bool) -> None:
        heard.append((channel.topic, added))

    cat.listeners.append(listen)
    return cat, heard


def note(cat: TopicCatalog, sender: Sender, frame: bytes) -> None:
    meta = read_metadata(frame)
    cat.note(sender, meta.topic, meta.type, frame)


def test_channels_follow_their_senders() -> None:
    cat, heard = catalog()
    a, b = Sender(1), Sender(2)
    note(cat, a, string_frame("/r/chat"))
    note(cat, a, string_frame("/r/chat"))
    note(cat, b, string_frame("/r/chat"))
    assert heard == [("/r/chat", True)]
    (channel,) = cat.channels()
    assert (channel.schema_name, channel.schema) == ("std_msgs/msg/String", "string data\n")
    cat.forget(a)
    assert heard == [("/r/chat", True)]  # b still sends it
    cat.forget(b)
    assert heard == [("/r/chat", True), ("/r/chat", False)] and cat.channels() == []
    note(cat, a, string_frame("/r/chat"))
    assert cat.channels()[0].id == channel.id  # same topic and type: same id again


def test_fragmented_and_compressed_topics_get_their_message_type() -> None:
    cat, heard = catalog()
    whole = scan_frame("/r/scan", 1, 5000)
    parts = fragments.split(whole, topic="/r/scan", message_id=7, max_fragment_bytes=4096,
                            no_drop=False)
    assert len(parts) > 2
    for part in parts[:-1]:
        note(cat, Sender(1), part)
    assert heard == []  # not complete yet: the type is not known
    note(cat, Sender(1), parts[-1])
    assert heard == [("/r/scan", True)] and cat.channels()[0].schema_name == SCAN_TYPE
    packed = compress(scan_frame("/r/scan_z", 1, 5000), codec=CompressionCodec.ZSTD,
                      topic="/r/scan_z", no_drop=False)
    note(cat, Sender(1), packed)
    assert heard[-1] == ("/r/scan_z", True)


def test_a_channel_lingers_after_its_last_sender_and_stays_when_sent_again() -> None:
    timers: list[Callable[[], None]] = []
    heard: list[tuple[str, bool]] = []
    cat = TopicCatalog(default_codec(), 1 << 24, linger_s=10.0,
                       call_later=lambda _delay_s, callback: timers.append(callback))
    cat.listeners.append(lambda channel, added: heard.append((channel.topic, added)))
    old, new = Sender(1), Sender(2)
    note(cat, old, string_frame("/r/chat"))
    cat.forget(old)  # the robot's connection closed...
    note(cat, new, string_frame("/r/chat"))  # ...and its next one sends the topic again
    timers.pop()()  # the first linger ends: void, the channel has a sender
    assert heard == [("/r/chat", True)] and len(cat.channels()) == 1
    cat.forget(new)
    note(cat, old, string_frame("/r/other"))
    timers.pop()()
    assert heard == [("/r/chat", True), ("/r/other", True), ("/r/chat", False)]
    assert [c.topic for c in cat.channels()] == ["/r/other"]


def test_topics_that_came_and_went_do_not_use_up_the_channels() -> None:
    # A relay whose robots come and go under new names saw more than MAX_CHANNELS
    # (topic, type) pairs in a few days of churn: the ids of every one were kept, and
    # from then on no new topic was offered to Foxglove at all (benchmarks/soak_relay.py).
    cat, heard = catalog()
    for k in range(MAX_CHANNELS):
        gone = Sender(k)
        note(cat, gone, string_frame(f"/robot{k}/chat"))
        cat.forget(gone)
    live = Sender(-1)
    note(cat, live, string_frame("/kept/chat"))
    assert [c.topic for c in cat.channels()] == ["/kept/chat"]  # before: [] (refused)
    kept = cat.channels()[0]
    note(cat, Sender(-2), string_frame("/new/chat"))
    assert heard[-1] == ("/new/chat", True) and cat.refused == 0
    new = next(c for c in cat.channels() if c.topic == "/new/chat")
    assert new.id > MAX_CHANNELS + 1  # ids of ended channels are never given again
    note(cat, live, string_frame("/kept/chat"))
    assert [c.id for c in cat.channels() if c.topic == "/kept/chat"] == [kept.id]
