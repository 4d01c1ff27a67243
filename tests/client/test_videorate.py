"""Unit tests of the video bitrate controller (pure, injected time)."""

from __future__ import annotations

from fleetctl.client.videorate import BitrateController, LinkSample

KBPS = 1000


def sample(rate_kBps: float = 0.0, higher: int = 0, dropped: int = 0,
           skipped: int = 0) -> LinkSample:
    return LinkSample(rate_kBps * 1000, higher, dropped, skipped)


def test_starts_at_the_maximum_without_an_estimate_and_at_the_cap_with_one() -> None:
    assert BitrateController(100 * KBPS, 1000 * KBPS).start(0.0, sample()) == 1000 * KBPS
    # 50 % of 100 kB/s = 400 kbit/s.
    assert BitrateController(100 * KBPS, 1000 * KBPS).start(0.0, sample(100)) == 400 * KBPS


def test_decides_once_per_period() -> None:
    rate = BitrateController(100 * KBPS, 1000 * KBPS)
    rate.start(0.0, sample(100))
    assert rate.update(0.5, sample(100, dropped=3)) is None
    assert rate.update(1.0, sample(100, dropped=3)) == 280 * KBPS  # 0.7 x 400


def test_congestion_backs_off_to_the_cap_or_by_the_factor() -> None:
    rate = BitrateController(100 * KBPS, 1000 * KBPS)
    rate.start(0.0, sample())
    # Skipped frames (the link did not take the last one): 0.7 x 1000, under the cap.
    assert rate.update(1.0, sample(1000, skipped=2)) == 700 * KBPS
    # The link's estimate says 50 kB/s: 50 % of it is 200 kbit/s.
    assert rate.update(2.0, sample(50, skipped=2, dropped=1)) == 200 * KBPS
    assert rate.congested_periods == 2
    # Never under the minimum.
    assert rate.update(3.0, sample(5, dropped=9)) == 100 * KBPS


def test_higher_priority_traffic_is_taken_off_the_link_first() -> None:
    rate = BitrateController(100 * KBPS, 1000 * KBPS)
    rate.start(0.0, sample(200, higher=0))
    # 200 kB/s of link, 100 kB/s of it used by higher priorities: 50 % of 100 kB/s.
    assert rate.update(1.0, sample(200, higher=100_000, dropped=1)) == 400 * KBPS


def test_without_congestion_it_probes_up_and_an_idle_estimate_does_not_pull_it_down() -> None:
    rate = BitrateController(100 * KBPS, 1000 * KBPS)
    rate.start(0.0, sample(50))  # 200 kbit/s
    # The estimate reads what the video itself sends (app-limited): no fall.
    assert rate.update(1.0, sample(25)) == 230 * KBPS
    assert rate.update(2.0, sample(25)) == 264_500
    # A higher estimate lifts it to the cap at once.
    assert rate.update(3.0, sample(200)) == 800 * KBPS
    assert rate.update(4.0, sample(200)) == 920 * KBPS
    assert rate.update(5.0, sample(200)) == 1000 * KBPS
    assert rate.update(6.0, sample(200)) is None  # at the maximum: no change


def test_reopening_codecs_change_only_on_large_moves_or_at_a_bound() -> None:
    rate = BitrateController(100 * KBPS, 1000 * KBPS, in_place=False)
    rate.start(0.0, sample(50))  # 200 kbit/s
    assert rate.update(1.0, sample(25)) is None  # +15 % < 25 %: kept
    assert rate.bitrate_bps == 200 * KBPS
    assert rate.update(2.0, sample(100)) == 400 * KBPS  # +100 %
    assert rate.update(3.0, sample(100, dropped=1)) == 280 * KBPS  # -30 %
    rate.bitrate_bps = 110 * KBPS
    assert rate.update(4.0, sample(100, dropped=2)) == 100 * KBPS  # the minimum, always


def test_the_cap_is_taken_on_the_wire_when_the_link_deflates() -> None:
    """The link's rate and the higher topics' bytes are frame bytes; when the link
    deflates a compressible cloud to a fifth, 500 kB/s of frame bytes is 100 kB/s on the
    wire, and the camera (which does not shrink) gets its share of that."""
    rate = BitrateController(10 * KBPS, 4000 * KBPS)
    deflating = LinkSample(500_000, 0, 0, 0, wire_share=0.2)
    assert rate.start(0.0, deflating) == 400 * KBPS  # 50 % of 100 kB/s on the wire
    congested = LinkSample(500_000, 300_000, 1, 0, wire_share=0.2)
    # Higher topics sent 300 kB of frame bytes in the second: (500 - 300) x 0.2 x 50 %
    # (under 0.7 x the current 400 kbit/s); in frame bytes it would have been 800.
    assert rate.update(1.0, congested) == 160 * KBPS
