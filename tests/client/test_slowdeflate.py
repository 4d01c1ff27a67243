"""When the robot deflates every message: by the link's rate on the wire, with a band."""

from __future__ import annotations

import pytest

from fleetctl.client.slowdeflate import SlowDeflateSettings, SlowLinkDeflate


def _now(d: SlowLinkDeflate, rate: float) -> bool:
    """decide() where time does not matter (the rule on at the first slow reading)."""
    return d.decide(rate, 0.0)


def _band(on_after_s: float = 0.0) -> SlowDeflateSettings:
    return SlowDeflateSettings(on_below_Bps=600_000, off_above_Bps=900_000,
                               on_after_s=on_after_s)


def test_a_slow_link_turns_it_on_a_fast_one_off_and_the_band_holds_either() -> None:
    d = SlowLinkDeflate(_band())
    assert not _now(d, 0.0)  # no rate yet: as it was
    assert not _now(d, 1_500_000)  # 12 Mbit/s
    assert not _now(d, 700_000)  # in the band: stays off
    assert _now(d, 375_000)  # 3 Mbit/s
    assert _now(d, 800_000)  # in the band: stays on
    assert _now(d, 0.0)
    assert not _now(d, 1_000_000)
    assert d.switches == 2


def test_on_only_when_the_link_stays_slow_not_on_one_cold_acknowledgement() -> None:
    """A new connection's first scan, acknowledged after a cold path on every hop, read
    2.1 Mbit/s on a 12 Mbit/s link: one reading, or a second of readings broken by a
    fast one, does not turn it on; a second of slow readings does."""
    d = SlowLinkDeflate(_band(on_after_s=1.0))
    assert SlowDeflateSettings().on_after_s == 1.0  # the default
    assert not d.decide(262_000, 10.0)  # the cold first acknowledgement
    assert not d.decide(400_000, 10.6)
    assert not d.decide(1_500_000, 10.9)  # the link's own rate: the clock starts over
    assert not d.decide(400_000, 11.0)
    assert not d.decide(700_000, 11.5)  # in the band is not slow either
    assert not d.decide(400_000, 11.6)
    assert not d.decide(400_000, 12.5)
    assert d.decide(400_000, 12.6)  # under the band for 1 s
    assert d.switches == 1
    assert not d.decide(1_000_000, 13.0)  # off at once, as before
    # A new connection starts the clock over: the last one's slow readings do not count.
    assert not d.decide(400_000, 14.0)
    d.new_connection()
    assert not d.decide(400_000, 15.0)
    assert not d.decide(0.0, 15.5)  # no rate: neither on nor a reset
    assert d.decide(400_000, 16.0)
    assert d.switches == 3


def test_it_judges_the_wire_rate_not_the_frame_rate_deflate_inflates() -> None:
    """A compressible cloud deflated to 5 % makes a 3 Mbit/s link look like 60 Mbit/s in
    frame bytes: deflate must stay on (turning it off sent raw fragments sized for the
    inflated rate)."""
    d = SlowLinkDeflate(_band())
    d.observe(200_000, 0)
    assert d.wire_share() == 1.0
    assert _now(d, 375_000)
    for _ in range(50):  # ~2.5 MB deflated to 5 %: the old traffic has faded
        d.observe(50_000, 47_500)
    assert d.wire_share() == pytest.approx(0.05, abs=0.01)
    assert _now(d, 7_500_000)  # 375 kB/s on the wire
    assert _now(d, 15_000_000)  # 750 kB/s on the wire: in the band
    # 1 MB/s on the wire, but measured on messages deflated to 5 %: a round trip's rate.
    assert _now(d, 20_000_000)
    for _ in range(50):  # incompressible data: the rate is the link's
        d.observe(50_000, 5_000)
    assert not _now(d, 1_200_000)  # 1.08 MB/s on the wire: a faster link
    assert d.switches == 2


def test_the_share_is_weighted_by_bytes_and_bounded() -> None:
    d = SlowLinkDeflate()
    d.observe(0, 0)  # nothing sent: ignored
    assert d.wire_share() == 1.0
    d.observe(1_000, -50)  # an incompressible message grew a little
    assert d.wire_share() == pytest.approx(1.05)
    d.observe(1_000, -1_000_000)  # a miscount cannot make the wire more than 2x
    assert d.wire_share() <= 2.0
    d.observe(1_000_000, 2_000_000)  # nor less than nothing
    assert 0.0 <= d.wire_share() < 0.1


def test_never_on_with_a_zero_threshold_and_a_band_must_be_ordered() -> None:
    off = SlowLinkDeflate(SlowDeflateSettings(on_below_Bps=0.0, on_after_s=0.0))
    assert not _now(off, 1.0)
    with pytest.raises(ValueError, match="on_below_Bps <= off_above_Bps"):
        SlowDeflateSettings(on_below_Bps=2.0, off_above_Bps=1.0)
    with pytest.raises(ValueError):
        SlowDeflateSettings(on_below_Bps=-1.0, off_above_Bps=1.0)
    with pytest.raises(ValueError, match="on_after_s"):
        SlowDeflateSettings(on_after_s=-1.0)
