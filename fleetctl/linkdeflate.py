"""permessage-deflate (RFC 7692) on the robot's uplink only.

Why: a fleet frame is self-describing (Robofleet convention): every message repeats its
type and topic strings, its metadata table and its vtables. For a 20 Hz pose that is 256
bytes on the wire for 76 bytes of CDR, and a fragment repeats it again. permessage-deflate
with context takeover turns each repetition into a back-reference into the previous
messages (a pose frame becomes about 50 bytes) and compresses the payload where it pays,
while the frames themselves stay exactly what they were: a server or client that does not
offer the extension gets today's bytes, byte for byte, and the relay forwards the
decompressed frame, so viewers and Robofleet-convention clients see no difference.

Why only one direction: the server relays one frame to many receivers; compressing per
receiver (context takeover is per connection) would cost the relay a deflate per delivery.
RFC 7692 section 6 lets a sender leave any message uncompressed (RSV1 clear), so the server
negotiates the extension and never compresses (:class:`InboundDeflate`). The robot
compresses only messages up to ``max_message_bytes`` (:class:`SmallMessageDeflate`): large
ones (clouds, images, video) are already compressed or barely compressible, and deflating
them would cost the client CPU (its bar: a 1 MB cloud at 10 Hz under 3 % of a core) for a
few percent; the per-topic ``compression:`` setting is the tool for those. On a slow link
(a few Mbit/s) it deflates everything: large messages travel there as fragments of about
one TCP segment (:mod:`fleetctl.client.segmentfill`), each repeating its metadata.

Sizes and CPU: docs/wire.md, "Uplink deflate".
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Sequence
from typing import Any, Protocol

from isal import isal_zlib
from websockets import frames
from websockets.extensions.permessage_deflate import (
    ClientPerMessageDeflateFactory,
    PerMessageDeflate,
    ServerPerMessageDeflateFactory,
)
from websockets.typing import ExtensionParameter

from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, fragment_payload_span, read_fragment_header
from fleetctl.wire.metadata import Metadata, read_root

# Messages up to this size are deflated by the robot. It is the size from which
# fleetctl.batched_connection masks and writes a frame in one pass: larger frames take
# that path untouched.
DEFAULT_MAX_MESSAGE_BYTES = 16 * 1024
# zlib level 1 for the slow-link rule's fragments (and for a peer that asks for no context
# takeover): on the e2e peer load it compresses within 2 % of level 6 at half the CPU
# (the redundancy that matters is back-references to earlier frames, which every level
# finds). memLevel 8 is zlib's default; websockets uses 5 to save 96 KiB per
# connection, which matters to a server with thousands of clients, not to one robot.
COMPRESS_SETTINGS: dict[str, int] = {"level": 1, "memLevel": 8}
# The robot's messages deflate with Intel ISA-L (PyPI ``isal``) at its level 2 while the
# link is fast: on the e2e peer load a 6 KB scan in 48 us instead of zlib level 1's 148 (to
# 3,462 bytes instead of 3,383), a pose in 10.6 us instead of 8.3 (38 bytes, not 34). The
# scan's deflate was the largest single step of the robot's per-message path (the floor
# against zenoh, docs/peers.md); what it writes is plain deflate, which the relay's zlib
# inflates. ISA-L has no Z_BLOCK flush, so the slow-link rule's fragments (three blocks
# each, SmallMessageDeflate._encode_blocks) keep zlib level 1, where the link's bytes,
# not the CPU, are short.
FAST_LEVEL = 2
# The history a robot's messages may refer to (2**15 = 32 KiB: a few scans' worth). It is
# also the inflate window the server keeps per connection that negotiated the extension.
WINDOW_BITS = 15


class FragmentObserver(Protocol):
    """Told the sizes of each fragment :class:`SmallMessageDeflate` deflates."""

    def observe(self, topic: str, payload_in: int, payload_out: int,
                frame_out: int) -> None: ...


class SmallMessageDeflate(PerMessageDeflate):
    """permessage-deflate that deflates fleet messages up to *max_message_bytes* only.

    Larger messages are sent as they are (RSV1 clear), which RFC 7692 allows per message;
    they do not enter the compression history, on either side. The size that decides is
    the fleet message's, not the WebSocket message's: a fragment (``Fragment`` frame) of
    a large message is not deflated however small the fragment. Why: the scheduler sizes
    fragments from the delivery rate it measures in frame bytes; if the fragments of a
    compressible cloud were deflated while small and sent raw once the measured rate made
    them large, the rate would swing with the compression and the fragments with it, and
    an urgent message would wait behind a raw 64 KB frame (measured: priority p99 37 ms
    instead of 6 ms in benchmarks/client_link.py (b)).

    On a slow link the robot sets :attr:`deflate_all` (:mod:`fleetctl.client.slowdeflate`
    decides it from the link's rate on the wire, which compression does not change): then
    every data message is deflated, fragments of large messages included. There the
    fragments are about one TCP segment (~3 ms of link time) and each repeats ~170 bytes
    of metadata, which context takeover turns into a back-reference; the link's bytes,
    not the CPU (bounded by that slow rate), are what is short. The sizes of each
    fragment deflated go to :attr:`fragment_observer`, which sizes the next ones.
    """

    def __init__(self, *args: Any, max_message_bytes: int, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.max_message_bytes = max_message_bytes
        self.deflate_all = False
        # Data bytes deflated messages did not put on the wire (their size in, less their
        # size out; negative for an incompressible one): with the frame bytes sent, the
        # robot's measure of its wire rate.
        self.saved_bytes = 0
        self._compressing_message = False  # the message being continued was deflated
        # Told the sizes of each fragment deflated as blocks (topic, payload in, payload
        # out, whole fragment out): the robot sizes its next fragments from them
        # (fleetctl.client.segmentfill).
        self.fragment_observer: FragmentObserver | None = None
        # Which deflater self.encoder is: ISA-L's while the link is fast, zlib's once the
        # slow-link rule deflates everything (the three-block fragments need Z_BLOCK).
        self._encoder_is_fast = False
        if not self.local_no_context_takeover:
            self._use_encoder(fast=True)

    def _use_encoder(self, fast: bool) -> None:
        """Start a new deflate context of the kind asked for, at a message boundary.

        A new one, never the other kind's old context: every message ends with a sync
        flush, so the stream may go on from any encoder, but an encoder's back-references
        point into what *it* compressed, and the inflater's window has since filled with
        what the other one did. The first messages after a switch carry no references
        (a pose ~150 bytes instead of ~35), once per switch of the slow-link rule.
        """
        wbits = -self.local_max_window_bits
        if fast:
            # websockets types its encoder as zlib's; ISA-L's has the same methods.
            self.encoder = isal_zlib.compressobj(  # type: ignore[assignment]
                FAST_LEVEL, wbits=wbits)
        else:
            self.encoder = zlib.compressobj(wbits=wbits, **self.compress_settings)
        self._encoder_is_fast = fast

    def passes_through(self, size: int) -> bool:
        """True when a whole data message of *size* bytes is sent untouched."""
        return not self.deflate_all and size > self.max_message_bytes

    def encode(self, frame: frames.Frame) -> frames.Frame:
        if frame.opcode in frames.CTRL_OPCODES:
            return frame
        if frame.opcode is frames.OP_CONT:
            compress = self._compressing_message
        else:
            compress = self.deflate_all or (
                not self.passes_through(len(frame.data))
                and _message_bytes(frame.data) <= self.max_message_bytes)
        self._compressing_message = compress and not frame.fin
        if not compress:
            return frame
        if (frame.opcode is not frames.OP_CONT and not self.local_no_context_takeover
                and self._encoder_is_fast == self.deflate_all):
            self._use_encoder(fast=not self.deflate_all)
        found = None
        if (self.deflate_all and frame.fin and frame.opcode is not frames.OP_CONT
                and not self.local_no_context_takeover):
            found = _fragment_payload(frame.data)
        out = super().encode(frame) if found is None else self._encode_blocks(frame, *found)
        self.saved_bytes += len(frame.data) - len(out.data)
        return out

    def _encode_blocks(self, frame: frames.Frame, topic: str,
                       payload: tuple[int, int]) -> frames.Frame:
        """A fragment as three deflate blocks: what precedes its payload, the payload, and
        what follows it (the same stream as ``super().encode``, cut differently).

        Why: zlib picks each block's coding as a whole. In one block, a random payload (a
        JPEG, a video frame) forces Huffman codes built for it, whose description and
        per-byte cost ate half of what the metadata's back-reference saved (1 KiB
        fragments of an image: 0.900 of their size on the wire); on its own the payload
        goes as a stored block (5 bytes) and the metadata as a few bytes of
        back-references: 0.861, the payload's own share being 0.842.
        """
        data, (start, end) = frame.data, payload
        enc = self.encoder
        head = enc.compress(data[:start]) + enc.flush(zlib.Z_BLOCK)
        body = enc.compress(data[start:end]) + enc.flush(zlib.Z_BLOCK)
        out = b"".join((head, body, enc.compress(data[end:]), enc.flush(zlib.Z_SYNC_FLUSH)))
        # A sync flush ends with an empty stored block, which RFC 7692 has removed.
        assert out.endswith(_SYNC_TAIL)
        sent = len(out) - len(_SYNC_TAIL)
        if self.fragment_observer is not None:
            self.fragment_observer.observe(topic, end - start, len(body), sent)
        return frames.Frame(frame.opcode, out[:sent], True, True, frame.rsv2, frame.rsv3)


_SYNC_TAIL = b"\x00\x00\xff\xff"


def _fragment_root(view: memoryview) -> tuple[Metadata, int] | None:
    """The metadata and root table of *view* when it is a Fragment frame; None for any
    other data."""
    try:
        meta, root = read_root(view)
    except WireError:
        return None
    return (meta, root) if meta.type == FRAGMENT_TYPE else None


def _fragment_payload(data: bytes | bytearray | memoryview,
                      ) -> tuple[str, tuple[int, int]] | None:
    """The topic of the Fragment frame *data* and where its payload lies; None for any
    other frame."""
    view = memoryview(data)
    found = _fragment_root(view)
    if found is not None:
        with contextlib.suppress(WireError):
            return found[0].topic, fragment_payload_span(view, found[1])
    return None


def _message_bytes(data: bytes | bytearray | memoryview) -> int:
    """The size of the fleet message *data* carries: a Fragment's whole message, else
    *data*'s own size (also for anything that is not a fleet frame)."""
    view = memoryview(data)
    found = _fragment_root(view)
    if found is not None:
        with contextlib.suppress(WireError):
            return read_fragment_header(view, found[1]).total_bytes
    return len(data)


class InboundDeflate(PerMessageDeflate):
    """permessage-deflate that decompresses what it receives and never compresses."""

    def passes_through(self, size: int) -> bool:
        """Always True: nothing this side sends is compressed."""
        del size
        return True

    def encode(self, frame: frames.Frame) -> frames.Frame:
        return frame


class RobotDeflateFactory(ClientPerMessageDeflateFactory):
    """The robot's offer: deflate from robot to server, nothing the other way.

    It asks for ``server_no_context_takeover`` (the server compresses nothing, so neither
    end keeps a context for that direction) and a 32 KiB window for its own messages.
    """

    def __init__(self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        super().__init__(server_no_context_takeover=True, client_max_window_bits=WINDOW_BITS,
                         compress_settings=dict(COMPRESS_SETTINGS))
        self.max_message_bytes = max_message_bytes

    def process_response_params(self, params: Sequence[ExtensionParameter],
                                accepted_extensions: Sequence[Any]) -> PerMessageDeflate:
        agreed = super().process_response_params(params, accepted_extensions)
        return SmallMessageDeflate(
            agreed.remote_no_context_takeover, agreed.local_no_context_takeover,
            agreed.remote_max_window_bits, agreed.local_max_window_bits,
            agreed.compress_settings, max_message_bytes=self.max_message_bytes)


class RelayDeflateFactory(ServerPerMessageDeflateFactory):
    """The server's answer to a permessage-deflate offer: inflate what comes in.

    It always answers ``server_no_context_takeover`` (it never compresses, so it keeps no
    compressor) and caps the client's window at 32 KiB, the inflate state it holds per
    connection. Browsers offer the extension too; what they send is small.
    """

    def __init__(self) -> None:
        super().__init__(server_no_context_takeover=True, client_max_window_bits=WINDOW_BITS)

    def process_request_params(self, params: Sequence[ExtensionParameter],
                               accepted_extensions: Sequence[Any],
                               ) -> tuple[list[ExtensionParameter], PerMessageDeflate]:
        answer, agreed = super().process_request_params(params, accepted_extensions)
        return answer, InboundDeflate(
            agreed.remote_no_context_takeover, agreed.local_no_context_takeover,
            agreed.remote_max_window_bits, agreed.local_max_window_bits)


def passes_through(extensions: Sequence[Any], size: int) -> bool:
    """True when no negotiated extension changes a data message of *size* bytes, so a
    frame can be serialized without them (:mod:`fleetctl.batched_connection`)."""
    return all(getattr(ext, "passes_through", lambda _: False)(size) for ext in extensions)
