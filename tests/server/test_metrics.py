from __future__ import annotations

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
