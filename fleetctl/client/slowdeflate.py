"""When the robot deflates every message on its uplink, fragments included: on a slow link.

Why: on a link of a few Mbit/s the scheduler cuts large messages (clouds, camera images,
video key frames) into ~1 KiB fragments (3 ms of link time each, so that an urgent message
waits behind at most one; once deflating, about one TCP segment:
:mod:`fleetctl.client.segmentfill`), and every fragment repeats its metadata: the Fragment table,
the topic and type strings, the vtables, ~170 bytes, so a camera on LTE spent ~15 % of its
link on headers. permessage-deflate with context takeover turns that repetition into a
back-reference; the robot's CPU is no objection there, because deflating costs per byte
and the link lets few bytes through (zlib level 1 on incompressible 1 KiB fragments:
~60 us each on a 2-core CI host, ~3 % of its core at 4 Mbit/s; docs/wire.md).

What decides must not move with the decision. The scheduler measures the link in frame
bytes (what it sends before compression), so deflating a compressible cloud makes the
link look faster, its fragments grow, and a rule on the fragment size or on that rate
would switch deflate off again: the swing that once put an urgent message behind a raw
64 KB frame (docs/wire.md, "Uplink deflate"). This rule uses the rate *on the wire*: the
frame-byte rate times the share of frame bytes that reach the wire (what
:class:`fleetctl.linkdeflate.SmallMessageDeflate` saved), which is the link's own speed
whatever is compressed. Deflate goes on below ``on_below_Bps`` and off above
``off_above_Bps`` (a band, so that the estimate's noise does not flip it).

It goes on only once the wire rate has stayed under ``on_below_Bps`` for ``on_after_s``
(:data:`DEFAULT_ON_AFTER_S`) of one connection's acknowledgements. A new connection's
first large message runs a cold path on every hop (the robot's first take and encode,
the relay's new route, the consumer's first frame: 10-57 ms for a scan that takes 3 ms a
second later), and one such acknowledgement read 2.1 Mbit/s on a 12 Mbit/s link in an
e2e `peer-fanout` round, and 4.3 Mbit/s 20 ms after a reconnect on a 4 Mbit/s link whose
16 KB token bucket the same light load otherwise crosses at 20-24 Mbit/s: the rule went
on at once, and on the fan-out link, sized by that rate, its 1 KiB fragments kept the
reading under the band for the rest of the round (scan p50 10.3 ms at 16 consumers
against 5.6-5.7 ms in the rounds where it stayed off; docs/peers.md). The busy rate
forgets a sample after ``link_rate_window_s`` (0.5 s), so a reading still low after
twice that is the link's.

It goes off only while deflate keeps at least :data:`TRUSTED_WIRE_SHARE` of the bytes. On
data it shrinks more (a cloud of zeros, one repeated letter), each message is a few
hundred bytes on the wire, acknowledged within a round trip, so the rate the scheduler
measures is the round trip's, not the link's: through a 4 Mbit/s token bucket a 64 KB
message of one letter, 640 bytes deflated, was acknowledged in ~1.5 ms and read as
0.86 MB/s on the wire; deflate went off and on 9-11 times in 10 s (an urgent message's
max 19 ms against 5-9). Such data is also what zlib deflates fastest (~10x faster than
random bytes), so staying on costs little.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# 5 Mbit/s: fragments there are 1 KiB (3 ms of link time is under 2 KiB), where their
# metadata is ~15 % of the link; above, they are 2 KiB or more and it is 8 % or less,
# for a CPU cost that grows with the rate.
DEFAULT_ON_BELOW_BPS = 625_000.0
DEFAULT_OFF_ABOVE_BPS = 937_500.0  # 7.5 Mbit/s
# Twice the scheduler's busy-rate window (0.5 s): a cold first acknowledgement has left
# the estimate by then (see above). On a link that is slow, deflating everything starts
# this much later after each connect, its fragments already sized by the rate meanwhile.
DEFAULT_ON_AFTER_S = 1.0
# The wire share is averaged over about this many recent frame bytes (a few hundred ms
# of a slow link), weighted by bytes.
SHARE_MEMORY_BYTES = 256 * 1024
# Below this share of frame bytes reaching the wire, the measured rate is not the link's
# (see above): deflate stays on.
TRUSTED_WIRE_SHARE = 0.5


@dataclass(frozen=True)
class SlowDeflateSettings:
    """The band of wire rates (bytes/s) in which the robot deflates every message, and
    how long (s) the rate must stay under the band's bottom before it does."""

    on_below_Bps: float = DEFAULT_ON_BELOW_BPS
    off_above_Bps: float = DEFAULT_OFF_ABOVE_BPS
    on_after_s: float = DEFAULT_ON_AFTER_S

    def __post_init__(self) -> None:
        if not 0 <= self.on_below_Bps <= self.off_above_Bps:
            raise ValueError("the slow-link deflate band needs 0 <= on_below_Bps <= "
                             f"off_above_Bps (got {self.on_below_Bps}, {self.off_above_Bps})")
        if not 0 <= self.on_after_s < math.inf:
            raise ValueError(f"on_after_s must be >= 0 s (got {self.on_after_s})")


class SlowLinkDeflate:
    """Decides, from what the link sent and what deflate saved, whether to deflate all.

    Args:
        settings: The band; ``on_below_Bps`` 0 never turns it on.
    """

    def __init__(self, settings: SlowDeflateSettings | None = None) -> None:
        self.settings = settings or SlowDeflateSettings()
        self.active = False
        self.switches = 0  # times it went on or off
        self._frame_weight = 0.0  # decayed frame bytes
        self._wire_weight = 0.0  # decayed wire bytes of the same frames
        self._slow_since: float | None = None  # since when every reading was under the band

    def wire_share(self) -> float:
        """Wire bytes per frame byte over the recent traffic (1.0 before any)."""
        if self._frame_weight <= 0:
            return 1.0
        return self._wire_weight / self._frame_weight

    def observe(self, frame_bytes: int, saved_bytes: int) -> None:
        """The link sent *frame_bytes* since the last call, of which deflate kept
        *saved_bytes* off the wire (negative: it added bytes)."""
        if frame_bytes <= 0:
            return
        wire_bytes = min(max(frame_bytes - saved_bytes, 0), 2 * frame_bytes)
        decay = math.exp(-frame_bytes / SHARE_MEMORY_BYTES)
        self._frame_weight = self._frame_weight * decay + frame_bytes
        self._wire_weight = self._wire_weight * decay + wire_bytes

    def new_connection(self) -> None:
        """A new connection: its rates start afresh, so a slow reading of the last one
        does not count towards :attr:`SlowDeflateSettings.on_after_s` (the state stays:
        the link is the same)."""
        self._slow_since = None

    def decide(self, frame_rate_Bps: float, now_s: float) -> bool:
        """Whether to deflate everything, given the link's rate in frame bytes (the
        scheduler's, 0 while it has none: the state then stays as it is) at *now_s*
        (monotonic seconds)."""
        if frame_rate_Bps <= 0:
            return self.active
        share = self.wire_share()
        wire_rate = frame_rate_Bps * share
        if self.active:
            if wire_rate > self.settings.off_above_Bps and share >= TRUSTED_WIRE_SHARE:
                self.active = False
                self.switches += 1
            return self.active
        if wire_rate >= self.settings.on_below_Bps:
            self._slow_since = None
            return False
        if self._slow_since is None:
            self._slow_since = now_s
        if now_s - self._slow_since >= self.settings.on_after_s:
            self.active = True
            self.switches += 1
            self._slow_since = None
        return self.active
