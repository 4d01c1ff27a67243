"""The protocol's messages (spec docs/spec.md) without sockets."""

from __future__ import annotations

import json
import struct

import pytest

from fleetctl.server.foxglove import messages as fx


def test_message_data_layout() -> None:
    frame = fx.message_data(0xDEADBEEF, 1_700_000_000_123_456_789, b"cdr")
    assert frame[0] == 0x01
    assert struct.unpack_from("<IQ", frame, 1) == (0xDEADBEEF, 1_700_000_000_123_456_789)
    assert frame[13:] == b"cdr"


def test_server_info_says_client_publish_only_when_allowed() -> None:
    info = json.loads(fx.server_info("s1", client_publish=True))
    assert info["op"] == "serverInfo" and info["sessionId"] == "s1"
    assert (info["capabilities"], info["supportedEncodings"]) == (["clientPublish"], ["cdr"])
    assert json.loads(fx.server_info("s1", client_publish=False))["capabilities"] == []


def test_channel_json() -> None:
    channel = fx.Channel(3, "/r/scan", "sensor_msgs/msg/LaserScan", "float32 x")
    assert json.loads(fx.advertise([channel]))["channels"] == [{
        "id": 3, "topic": "/r/scan", "encoding": "cdr", "schemaName":
        "sensor_msgs/msg/LaserScan", "schema": "float32 x", "schemaEncoding": "ros2msg"}]
    assert json.loads(fx.unadvertise([3])) == {"op": "unadvertise", "channelIds": [3]}


def test_requests_parse() -> None:
    assert fx.parse_request('{"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 2}]}'
                            ) == fx.Subscribe([(1, 2)])
    assert fx.parse_request('{"op": "unsubscribe", "subscriptionIds": [1]}') == \
        fx.Unsubscribe([1])
    advertised = fx.parse_request(json.dumps({"op": "advertise", "channels": [
        {"id": 4, "topic": "/g", "encoding": "cdr", "schemaName": "std_msgs/msg/String"}]}))
    assert advertised == fx.ClientAdvertise([fx.ClientChannel(4, "/g", "cdr",
                                                              "std_msgs/msg/String")])
    assert fx.parse_request('{"op": "unadvertise", "channelIds": [4]}') == \
        fx.ClientUnadvertise([4])


@pytest.mark.parametrize("text", [
    "", "nope", "[]", "[" * 100_000, '{"op": 1}', '{"op": "getParameters"}',
    '{"op": "subscribe"}', '{"op": "subscribe", "subscriptions": [{"id": true, '
    '"channelId": 1}]}', '{"op": "subscribe", "subscriptions": [{"id": 4294967296, '
    '"channelId": 1}]}', '{"op": "unsubscribe", "subscriptionIds": [-1]}',
    '{"op": "advertise", "channels": [{"id": 1, "topic": "", "encoding": "cdr", '
    '"schemaName": "x"}]}',
    # fuzzing: a lone surrogate topic reached RE2 (may_send) and raised UnicodeEncodeError
    '{"op": "advertise", "channels": [{"id": 9, "topic": "/husky1/\\ud800", "encoding": '
    '"cdr", "schemaName": "std_msgs/String"}]}', json.dumps({"op": "unsubscribe", "subscriptionIds":
                                        list(range(fx.MAX_ITEMS_PER_REQUEST + 1))}),
])
def test_bad_requests_are_protocol_errors(text: str) -> None:
    with pytest.raises(fx.ProtocolError):
        fx.parse_request(text)


def test_client_data() -> None:
    channel_id, payload = fx.parse_client_data(struct.pack("<BI", 1, 9) + b"xyz")
    assert (channel_id, bytes(payload)) == (9, b"xyz")
    for frame in (b"", b"\x01\x00", struct.pack("<BI", 2, 9)):
        with pytest.raises(fx.ProtocolError):
            fx.parse_client_data(frame)
