"""Unit tests of the tc command building and the shaper's state machine (no root needed)."""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from fleetctl.deploy.dockercli import Completed
from fleetctl.deploy.shaping import (
    Capabilities,
    LinkShaper,
    RateSpec,
    cut_argv,
    detect,
    mbit,
    rate_argvs,
)
from fleetctl.errors import EnvironmentMissing, FleetError


class FakeTc:
    """Records commands; fails those whose qdisc kind is in *missing* (like a kernel)."""

    def __init__(self, missing: Sequence[str] = ()) -> None:
        self.missing = set(missing)
        self.calls: list[list[str]] = []

    def __call__(self, argv: Sequence[str]) -> Completed:
        self.calls.append(list(argv))
        bad = any(kind in argv for kind in self.missing)
        err = "Error: Specified qdisc kind is unknown." if bad else ""
        return Completed(tuple(argv), 2 if bad else 0, "", err)


def test_detect_without_netem_picks_tbf_and_bfifo() -> None:
    tc = FakeTc(missing=["netem"])
    caps = detect(tc, "eth1")
    assert caps == Capabilities(netem=False, tbf=True, htb=True, bfifo=True)
    assert caps.rate_method == "tbf"
    assert caps.cut_method == "bfifo-limit-0"
    assert caps.describe() == "netem: no; rate: tbf; cut: bfifo-limit-0"
    assert tc.calls[-1] == ["tc", "qdisc", "del", "dev", "eth1", "root"]


def test_fallbacks_when_kinds_are_missing() -> None:
    assert Capabilities(netem=True, tbf=False, htb=False, bfifo=False).rate_method == "netem"
    assert Capabilities(netem=True, tbf=False, htb=False, bfifo=False).cut_method == (
        "netem-loss-100"
    )
    assert Capabilities(netem=False, tbf=False, htb=True, bfifo=True).rate_method == "htb"
    none = Capabilities(netem=False, tbf=False, htb=False, bfifo=False)
    with pytest.raises(EnvironmentMissing):
        _ = none.rate_method
    with pytest.raises(EnvironmentMissing):
        _ = none.cut_method


def test_tbf_burst_covers_one_tick_of_traffic() -> None:
    assert RateSpec(mbit(100)).burst_bytes == 50_000
    assert RateSpec(mbit(4)).burst_bytes == 16 * 1024
    (cmd,) = rate_argvs("eth0", RateSpec(mbit(12), 400), "tbf", live=False)
    assert cmd == ["tc", "qdisc", "replace", "dev", "eth0", "root", "tbf", "rate",
                   "12000000bit", "burst", "16384", "latency", "400ms"]


def test_live_change_uses_change_not_replace() -> None:
    (cmd,) = rate_argvs("eth0", RateSpec(mbit(4)), "tbf", live=True)
    assert cmd[:3] == ["tc", "qdisc", "change"]
    htb = rate_argvs("eth0", RateSpec(mbit(4)), "htb", live=False)
    assert [c[1] for c in htb] == ["qdisc", "class"]
    assert rate_argvs("eth0", RateSpec(mbit(4)), "htb", live=True)[0][:3] == [
        "tc", "class", "change"]


def test_bad_specs_and_methods_are_errors() -> None:
    with pytest.raises(FleetError, match="rate_bit_s"):
        RateSpec(0)
    with pytest.raises(FleetError, match="queue_latency_ms"):
        RateSpec(1000, 0)
    with pytest.raises(FleetError, match="unknown rate method"):
        rate_argvs("eth0", RateSpec(1000), "cake", live=False)
    with pytest.raises(FleetError, match="unknown cut method"):
        cut_argv("eth0", "unplug")


def test_shaper_cut_and_restore_returns_to_the_last_rate() -> None:
    tc = FakeTc()
    shaper = LinkShaper(tc, "eth1", Capabilities(netem=False, tbf=True, htb=True, bfifo=True))
    shaper.set_rate(RateSpec(mbit(12)))
    shaper.set_rate(RateSpec(mbit(6)))  # live change
    shaper.cut()
    shaper.restore()
    ops = [(c[2], c[6]) for c in tc.calls]
    assert ops == [("replace", "tbf"), ("change", "tbf"), ("replace", "bfifo"),
                   ("replace", "tbf")]
    assert "6000000bit" in tc.calls[-1]
    shaper.clear()
    assert tc.calls[-1][2] == "del"


def test_shaper_reports_tc_failures() -> None:
    tc = FakeTc(missing=["tbf"])
    shaper = LinkShaper(tc, "eth1", Capabilities(netem=False, tbf=True, htb=False, bfifo=True))
    with pytest.raises(FleetError, match="qdisc kind is unknown"):
        shaper.set_rate(RateSpec(mbit(1)))
