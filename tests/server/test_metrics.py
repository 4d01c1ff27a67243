from __future__ import annotations

import pytest

from fleetctl.server import metrics as m


def test_render_exposition_and_label_bound(monkeypatch: object) -> None:
    mt = m.Metrics()
    mt.count_in('/a"b', 10)
    mt.count_out("/a", 5)
    mt.count_drop("/a", 2)
    mt.count_error("bad_regex")
    mt.count_close(4403)
    text = mt.render([("fleetctl_outbound_queue_frames", "Depth.", {"conn#1": 3.0})])
    assert 'fleetctl_messages_in_total{topic="/a\\"b"} 1' in text
    assert 'fleetctl_bytes_in_total{topic="/a\\"b"} 10' in text
    assert 'fleetctl_drops_total{topic="/a"} 2' in text
    assert 'fleetctl_closes_total{code="4403"} 1' in text
    assert 'fleetctl_outbound_queue_frames{connection="conn#1"} 3.0' in text
    assert "# TYPE fleetctl_messages_out_total counter" in text
    for i in range(m.MAX_TOPIC_LABELS + 10):
        mt.count_in(f"/t{i}", 1)
    assert len(mt.messages_in) == m.MAX_TOPIC_LABELS + 1  # the bound plus <other>
    assert mt.messages_in[m.OTHER] > 0


def test_session_drops_and_session_gauges() -> None:
    mt = m.Metrics()
    mt.count_session_drop("alice/console", "/a")
    mt.count_session_drop("alice/console", "/a")
    text = mt.render(labelled=[("fleetctl_sessions", "By state.", "state", {"online": 1.0})])
    assert ('fleetctl_session_mailbox_drops_total{session="alice/console",topic="/a"} 2'
            in text)
    assert 'fleetctl_sessions{state="online"} 1.0' in text
    for i in range(m.MAX_TOPIC_LABELS + 5):
        mt.count_session_drop("s", f"/t{i}")
    assert len(mt.session_drops) == m.MAX_TOPIC_LABELS + 1  # the bound plus <other>


def test_a_full_label_table_forgets_topics_idle_for_an_hour(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The first MAX_TOPIC_LABELS topics kept their labels for good: on a relay whose
    robots come and go under new names, /metrics showed gone robots' topics and counted
    every new one under <other> (the relay soak filled the table in 12 minutes)."""
    monkeypatch.setattr(m, "MAX_TOPIC_LABELS", 3)
    metrics = m.Metrics()
    for topic in ("/gone1/scan", "/gone2/scan", "/live/scan"):
        metrics.count_in(topic, 10)
        metrics.count_out(topic, 10)
    metrics.count_session_drop("gone1", "/gone1/goal")
    assert metrics.forget_idle(0.0) == 0
    metrics.count_in("/new/scan", 10)
    assert "/new/scan" not in metrics.messages_in  # full: counted under <other>
    for minute in range(1, 60):
        metrics.count_in("/live/scan", 10)  # /live keeps counting; the others went
        assert metrics.forget_idle(minute * 60.0) == 0, minute
    metrics.count_in("/live/scan", 10)
    assert metrics.forget_idle(60 * 60.0) == 2  # /gone1 and /gone2, idle an hour
    assert set(metrics.messages_in) == {"/live/scan", m.OTHER}
    assert "/gone1/scan" not in metrics.bytes_out | metrics.messages_out | metrics.bytes_in
    assert metrics.session_drops == {("gone1", "/gone1/goal"): 1}  # its table is not full
    metrics.count_in("/new/scan", 10)
    assert metrics.messages_in["/new/scan"] == 1  # room again: a label of its own
    assert "fleetctl_metric_labels_forgotten_total 2" in metrics.render()


def test_forget_idle_looks_once_a_sweep_period() -> None:
    metrics = m.Metrics()
    metrics.count_in("/a", 1)
    metrics.forget_idle(0.0)
    metrics.count_in("/a", 1)
    metrics.forget_idle(m.IDLE_SWEEP_PERIOD_S / 2)  # too soon: not looked at
    assert metrics._topics_moved["/a"] == ((1, 0, 0), 0.0)
    metrics.forget_idle(m.IDLE_SWEEP_PERIOD_S)
    assert metrics._topics_moved["/a"] == ((2, 0, 0), m.IDLE_SWEEP_PERIOD_S)


def test_a_full_session_drop_table_forgets_its_idle_pairs(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(m, "MAX_TOPIC_LABELS", 2)
    metrics = m.Metrics()
    metrics.count_session_drop("old", "/old/goal")
    metrics.count_session_drop("live", "/live/goal")
    metrics.count_in("/topic", 1)  # the topics' table is not full: kept however idle
    metrics.forget_idle(0.0)
    metrics.count_session_drop("live", "/live/goal")
    assert metrics.forget_idle(m.IDLE_LABEL_S) == 1
    assert metrics.session_drops == {("live", "/live/goal"): 2}
    assert metrics.messages_in == {"/topic": 1}
