"""When the robot deflates every message: by the link's rate on the wire, with a band."""

from __future__ import annotations

import pytest

from fleetctl.client.slowdeflate import SlowDeflateSettings, SlowLinkDeflate


def test_a_slow_link_turns_it_on_a_fast_one_off_and_the_band_holds_either() -> None:
    d = SlowLinkDeflate(SlowDeflateSettings(on_below_Bps=600_000, off_above_Bps=900_000))
    assert not d.decide(0.0)  # no rate yet: as it was
    assert not d.decide(1_500_000)  # 12 Mbit/s
    assert not d.decide(700_000)  # in the band: stays off
    assert d.decide(375_000)  # 3 Mbit/s
    assert d.decide(800_000)  # in the band: stays on
    assert d.decide(0.0)
    assert not d.decide(1_000_000)
    assert d.switches == 2


def test_it_judges_the_wire_rate_not_the_frame_rate_deflate_inflates() -> None:
    """A compressible cloud deflated to 5 % makes a 3 Mbit/s link look like 60 Mbit/s in
    frame bytes: deflate must stay on (turning it off sent raw fragments sized for the
    inflated rate)."""
    d = SlowLinkDeflate(SlowDeflateSettings(on_below_Bps=600_000, off_above_Bps=900_000))
    d.observe(200_000, 0)
    assert d.wire_share() == 1.0
    assert d.decide(375_000)
    for _ in range(50):  # ~2.5 MB deflated to 5 %: the old traffic has faded
        d.observe(50_000, 47_500)
    assert d.wire_share() == pytest.approx(0.05, abs=0.01)
    assert d.decide(7_500_000)  # 375 kB/s on the wire
    assert d.decide(15_000_000)  # 750 kB/s on the wire: in the band
    # 1 MB/s on the wire, but measured on messages deflated to 5 %: a round trip's rate.
    assert d.decide(20_000_000)
    for _ in range(50):  # incompressible data: the rate is the link's
        d.observe(50_000, 5_000)
    assert not d.decide(1_200_000)  # 1.08 MB/s on the wire: a faster link
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
    off = SlowLinkDeflate(SlowDeflateSettings(on_below_Bps=0.0))
    assert not off.decide(1.0)
    with pytest.raises(ValueError, match="on_below_Bps <= off_above_Bps"):
        SlowDeflateSettings(on_below_Bps=2.0, off_above_Bps=1.0)
    with pytest.raises(ValueError):
        SlowDeflateSettings(on_below_Bps=-1.0, off_above_Bps=1.0)
