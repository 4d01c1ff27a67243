"""The video bitrate, following the link (pure: injected time, no I/O).

Every ``period_s`` (1 s) :class:`BitrateController` sets a camera's encoder bitrate from
what the link tells the client (:class:`LinkSample`):

- the **cap**: ``share`` (50 %) of what the link delivers after the topics of higher
  priority took theirs, ``share x (estimate - higher)``, where *estimate* is the
  scheduler's link rate (bytes acknowledged over busy time, held at its maximum for a few
  seconds: :class:`fleetctl.client.estimators.BusyRate`) and *higher* what topics of
  higher priority sent in the period. The other half stays for the topics of equal and
  lower priority, and for the keyframes' bursts.
- **congestion**: the link dropped a frame of this topic, or the camera had to skip
  frames because the previous one was still waiting for the link. Then the bitrate goes
  to ``min(cap, decrease x bitrate)`` at once: on a saturated link the estimate is the
  link's rate.
- **no congestion**: the bitrate rises to the cap when the cap is higher, and otherwise
  probes up by ``increase`` (x 1.15 per second). The cap does not lower it then: an
  estimate taken while the link was mostly idle only measures what the client sent (a
  30 Hz stream of 4 KB frames over a 50 ms RTT link reads as exactly its own rate), and
  following it down would halve the video every second on an idle link.

Always within ``[min_bps, max_bps]`` (the entry's ``min_bitrate_kbps`` and
``max_bitrate_kbps``). Codecs that reopen their encoder for a new bitrate (vp8, vp9, av1:
a keyframe each time) change only on moves of ``reopen_step`` (25 %) or more.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["BitrateController", "LinkSample"]


@dataclass(frozen=True)
class LinkSample:
    """What the link says about one video topic (cumulative counters).

    Attributes:
        link_rate_Bps: The link's estimated rate (bytes/s); 0 before any estimate.
        higher_priority_sent_bytes: Bytes sent so far by topics of higher priority.
        dropped: Frames of this topic the link dropped so far.
        skipped: Camera frames not encoded so far because the link had not taken the
            previous one yet.
        wire_share: Bytes on the wire per byte the link sent, lately (the rate and the
            counts are the link's frame bytes, before its deflate; a video frame does not
            shrink, so its share of the link is counted on the wire).
    """

    link_rate_Bps: float
    higher_priority_sent_bytes: int
    dropped: int
    skipped: int
    wire_share: float = 1.0


class BitrateController:
    """Chooses a camera's bitrate once per period (see the module docstring).

    Args:
        min_bps: Lowest bitrate (bits/s).
        max_bps: Highest bitrate (bits/s), also the start before any estimate.
        share: Fraction of the link (after higher priorities) the video may take.
        period_s: Seconds between decisions.
        increase: Factor per period while the link keeps up.
        decrease: Factor on congestion.
        reopen_step: Smallest relative change applied when *in_place* is False.
        in_place: The encoder takes a new bitrate without a keyframe (h264).
    """

    def __init__(self, min_bps: int, max_bps: int, *, share: float = 0.5,
                 period_s: float = 1.0, increase: float = 1.15, decrease: float = 0.7,
                 reopen_step: float = 0.25, in_place: bool = True) -> None:
        self.min_bps = min_bps
        self.max_bps = max(min_bps, max_bps)
        self.share = share
        self.period_s = period_s
        self.increase = increase
        self.decrease = decrease
        self.reopen_step = reopen_step
        self.in_place = in_place
        self.bitrate_bps = self.max_bps
        self.congested_periods = 0
        self._last_s: float | None = None
        self._last: LinkSample | None = None

    def start(self, now_s: float, sample: LinkSample) -> int:
        """Begin at the cap when the link already has an estimate, else at the maximum.

        Returns:
            The bitrate to open the encoder with (bits/s).
        """
        self._last_s, self._last = now_s, sample
        if sample.link_rate_Bps > 0:
            self.bitrate_bps = self._clamp(
                self.share * 8 * sample.link_rate_Bps * sample.wire_share)
        return self.bitrate_bps

    def update(self, now_s: float, sample: LinkSample) -> int | None:
        """Decide, if a period has passed since the last decision.

        Returns:
            The new bitrate (bits/s) when it changed, else None.
        """
        if self._last_s is None or self._last is None:
            self.start(now_s, sample)
            return None
        elapsed = now_s - self._last_s
        if elapsed < self.period_s:
            return None
        last = self._last
        self._last_s, self._last = now_s, sample
        congested = sample.dropped > last.dropped or sample.skipped > last.skipped
        cap = self._cap(sample, last, elapsed)
        current = self.bitrate_bps
        if congested:
            self.congested_periods += 1
            target = min(cap, current * self.decrease)
        elif cap > current:
            target = cap
        else:
            target = current * self.increase
        return self._apply(self._clamp(target))

    def _cap(self, sample: LinkSample, last: LinkSample, elapsed_s: float) -> float:
        """``share x (estimate - higher priority use)`` in bits/s on the wire; infinite
        without an estimate.

        Both are measured in the bytes the link sent before its deflate; on a slow link
        that deflates everything, a compressible cloud beside the camera makes the link
        look several times faster in those bytes than on the wire, while a video frame
        does not shrink: so they are taken on the wire.
        """
        if sample.link_rate_Bps <= 0:
            return float("inf")
        higher_Bps = max(0, sample.higher_priority_sent_bytes
                         - last.higher_priority_sent_bytes) / elapsed_s
        return (self.share * 8 * max(0.0, sample.link_rate_Bps - higher_Bps)
                * sample.wire_share)

    def _clamp(self, bps: float) -> int:
        return round(min(self.max_bps, max(self.min_bps, bps)))

    def _apply(self, target: int) -> int | None:
        current = self.bitrate_bps
        if target == current:
            return None
        # A reopening encoder pays a keyframe per change: only for real moves, and always
        # for reaching a bound (else a bitrate 20 % above min_bps could never get there).
        small = abs(target - current) < self.reopen_step * current
        if not self.in_place and small and target not in (self.min_bps, self.max_bps):
            return None
        self.bitrate_bps = target
        return target
