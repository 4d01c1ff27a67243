"""HTTP/1.0 requests (a load balancer's health check) read by websockets' HTTP/1.1 parser.

websockets parses request lines of HTTP/1.1 only (``websockets.http11.Request.parse``:
"unsupported protocol; expected HTTP/1.1"), so ``GET /healthz HTTP/1.0`` failed the
handshake and the connection was closed without an answer: a health check that speaks
HTTP/1.0 (HAProxy's ``option httpchk`` does by default) saw the relay as down.

:class:`RequestLine` holds back a connection's first bytes until its request line is
complete and gives the parser an HTTP/1.0 line as HTTP/1.1. That is safe for what the
server answers without an upgrade: a GET without a body, one response, then the
connection is closed (``Connection: close``), which is HTTP/1.0's own default. A response
says ``HTTP/1.1``, which an HTTP/1.0 client reads (RFC 9110 6.2: a server sends its own
version). A WebSocket upgrade needs HTTP/1.1 (RFC 6455 4.1); the server refuses one that
came as HTTP/1.0 (:attr:`RequestLine.http10` tells it).
"""

from __future__ import annotations

from websockets.http11 import MAX_LINE_LENGTH

_HTTP10 = b" HTTP/1.0"
_HTTP11 = b" HTTP/1.1"


class RequestLine:
    """The request line of one connection, rewritten from HTTP/1.0 when it is one.

    Attributes:
        done: The request line went to the parser (everything after passes as is).
        http10: The request came as HTTP/1.0.
    """

    __slots__ = ("_held", "done", "http10")

    def __init__(self) -> None:
        self._held = b""
        self.done = False
        self.http10 = False

    def feed(self, data: bytes) -> bytes:
        """Take bytes received; return those to give the HTTP parser now (``b""`` while
        the request line is incomplete: the parser would wait for it too). A line longer
        than websockets' limit goes on unchanged, for the parser to refuse."""
        if self.done:
            return data
        held = self._held + data
        end = held.find(b"\r\n")  # websockets takes CRLF-terminated lines only
        if end < 0 and len(held) <= MAX_LINE_LENGTH:
            self._held = held
            return b""
        self.done = True
        self._held = b""
        if end >= 0 and held[:end].endswith(_HTTP10):
            self.http10 = True
            return held[:end - len(_HTTP10)] + _HTTP11 + held[end:]
        return held
