"""Foxglove WebSocket protocol v1 messages (github.com/foxglove/ws-protocol, docs/spec.md).

Pure functions, no I/O: JSON texts and binary frames the server sends, and the parsing of
what a client sends into typed requests. Only the parts the relay implements: Server Info,
Status, Advertise, Unadvertise and Message Data out; Subscribe, Unsubscribe, Client
Advertise, Client Unadvertise and Client Message Data in.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

SUBPROTOCOL = "foxglove.websocket.v1"
SERVER_NAME = "fleetctl"
# spec "Status": level 0 info, 1 warning, 2 error.
INFO, WARNING, ERROR = 0, 1, 2
# spec "Binary messages": opcode 0x01 is Message Data (server) and Client Message Data.
OP_MESSAGE_DATA = 0x01
_MESSAGE_HEADER = struct.Struct("<BIQ")  # opcode, subscription id u32, receive time u64 ns
_CLIENT_HEADER = struct.Struct("<BI")  # opcode, client channel id u32
_U32_MAX = 0xFFFFFFFF
# Why: a Foxglove client sends a handful of requests at a time; larger texts are refused
# before parsing (a JSON bomb costs nothing).
MAX_TEXT_CHARS = 256 * 1024
MAX_ITEMS_PER_REQUEST = 1024


class ProtocolError(Exception):
    """A client message the server cannot take; its text goes into a Status (error)."""


@dataclass(frozen=True)
class Channel:
    """A server channel (spec "Advertise"): one topic with one ROS 2 type."""

    id: int
    topic: str
    schema_name: str
    schema: str

    def as_json(self) -> dict[str, Any]:
        return {"id": self.id, "topic": self.topic, "encoding": "cdr",
                "schemaName": self.schema_name, "schema": self.schema,
                "schemaEncoding": "ros2msg"}


@dataclass(frozen=True)
class Subscribe:
    """``subscribe``: ``(subscription id, channel id)`` pairs."""

    subscriptions: list[tuple[int, int]]


@dataclass(frozen=True)
class Unsubscribe:
    """``unsubscribe``: subscription ids."""

    ids: list[int]


@dataclass(frozen=True)
class ClientChannel:
    """One channel of a Client Advertise."""

    id: int
    topic: str
    encoding: str
    schema_name: str


@dataclass(frozen=True)
class ClientAdvertise:
    """Client ``advertise``."""

    channels: list[ClientChannel]


@dataclass(frozen=True)
class ClientUnadvertise:
    """Client ``unadvertise``: client channel ids."""

    ids: list[int]


Request = Subscribe | Unsubscribe | ClientAdvertise | ClientUnadvertise


def server_info(session_id: str, *, client_publish: bool) -> str:
    """Server Info: the first message on every connection (spec "Server Info")."""
    info: dict[str, Any] = {"op": "serverInfo", "name": SERVER_NAME, "capabilities": [],
                            "metadata": {}, "sessionId": session_id}
    if client_publish:
        info["capabilities"] = ["clientPublish"]
        info["supportedEncodings"] = ["cdr"]
    return json.dumps(info)


def status(level: int, message: str) -> str:
    """A Status message (spec "Status"); *level* is :data:`INFO`, :data:`WARNING` or
    :data:`ERROR`."""
    return json.dumps({"op": "status", "level": level, "message": message})


def advertise(channels: list[Channel]) -> str:
    """Advertise *channels* (spec "Advertise")."""
    return json.dumps({"op": "advertise", "channels": [c.as_json() for c in channels]})


def unadvertise(ids: list[int]) -> str:
    """Unadvertise channel *ids* (spec "Unadvertise")."""
    return json.dumps({"op": "unadvertise", "channelIds": ids})


def message_data(subscription_id: int, receive_time_ns: int, payload: bytes) -> bytes:
    """A binary Message Data frame (spec "Message Data"): opcode, subscription id, receive
    timestamp in ns since the epoch, then *payload* as is."""
    return _MESSAGE_HEADER.pack(OP_MESSAGE_DATA, subscription_id, receive_time_ns) + payload


def parse_client_data(frame: bytes) -> tuple[int, memoryview]:
    """Split a binary Client Message Data frame into ``(client channel id, payload)``.

    Raises:
        ProtocolError: Another opcode, or a frame shorter than its header.
    """
    if len(frame) < _CLIENT_HEADER.size:
        raise ProtocolError(f"binary message of {len(frame)} bytes: shorter than the "
                            "5-byte Client Message Data header")
    opcode, channel_id = _CLIENT_HEADER.unpack_from(frame)
    if opcode != OP_MESSAGE_DATA:
        raise ProtocolError(f"unsupported binary opcode 0x{opcode:02x}")
    return channel_id, memoryview(frame)[_CLIENT_HEADER.size:]


def parse_request(text: str) -> Request:
    """Parse one client JSON text.

    Raises:
        ProtocolError: Not a JSON object, an unknown or unsupported ``op``, or a field of
            the wrong shape.
    """
    data: Any = None
    if len(text) <= MAX_TEXT_CHARS:
        try:
            data = json.loads(text)
        except (ValueError, RecursionError):  # RecursionError: "[[[[...": deep nesting
            data = None
    if not isinstance(data, dict):
        raise ProtocolError("a text message must be a JSON object with an 'op' field")
    op = data.get("op")
    if op == "subscribe":
        return Subscribe([(_u32(s, "id"), _u32(s, "channelId"))
                          for s in _items(data, "subscriptions")])
    if op == "unsubscribe":
        return Unsubscribe([_as_u32(i, "subscriptionIds") for i in _items(data,
                                                                           "subscriptionIds")])
    if op == "advertise":
        return ClientAdvertise([_client_channel(c) for c in _items(data, "channels")])
    if op == "unadvertise":
        return ClientUnadvertise([_as_u32(i, "channelIds") for i in _items(data, "channelIds")])
    raise ProtocolError(f"unsupported op {str(op)[:64]!r}: this server implements subscribe, "
                        "unsubscribe, advertise and unadvertise")


def _items(data: dict[str, Any], key: str) -> list[Any]:
    items = data.get(key)
    if not isinstance(items, list) or len(items) > MAX_ITEMS_PER_REQUEST:
        raise ProtocolError(f"{key!r} must be a list of at most {MAX_ITEMS_PER_REQUEST} items")
    return items


def _as_u32(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= _U32_MAX:
        raise ProtocolError(f"{key!r} must hold unsigned 32-bit integers")
    number: int = value
    return number


def _u32(item: Any, key: str) -> int:
    if not isinstance(item, dict):
        raise ProtocolError(f"expected an object with {key!r}")
    return _as_u32(item.get(key), key)


def _text(item: dict[str, Any], key: str) -> str:
    value = item.get(key)
    if not isinstance(value, str) or not value or len(value) > 1024:
        raise ProtocolError(f"channel field {key!r} must be a non-empty string")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:  # JSON's "\ud800" escape: a lone surrogate, in no topic
        raise ProtocolError(f"channel field {key!r} is not UTF-8 text (a lone surrogate "
                            "code point)") from None
    return value


def _client_channel(item: Any) -> ClientChannel:
    channel_id = _u32(item, "id")
    return ClientChannel(channel_id, _text(item, "topic"), _text(item, "encoding"),
                         _text(item, "schemaName"))
