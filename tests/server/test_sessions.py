"""Named sessions driven through the relay core, without sockets (fleetctl.server.sessions)."""

from __future__ import annotations

import json
import logging
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.server.sessions import (
    BadSessionName,
    Mailbox,
    check_session_name,
    session_metric_id,
)
from fleetctl.server.sessionstore import SessionStore
from fleetctl.wire import fragments
from fleetctl.wire.control import encode_subscription
from tests.server.conftest import ALICE_TOKEN, BOB_TOKEN, auth_map, authed_peer, closes, raw_peer
from tests.support import ManualClock, decode_text, string_frame

METRIC_ID = session_metric_id((("alice",), "console"))  # opaque: no e-mail in /metrics


def make_core(db: Path | None = None, clock: ManualClock | None = None, **limits: Any) -> RelayCore:
    config = ServerConfig(limits=ServerLimits(**limits))
    return RelayCore(config, auth_map(), RobotRegistry(db, 5.0), Metrics(),
                     clock=clock or ManualClock())


def drain(p: Peer) -> tuple[list[dict[str, Any]], list[bytes]]:
    """(text frames as JSON, binary frames) the peer would be sent, in order."""
    texts: list[dict[str, Any]] = []
    frames: list[bytes] = []
    for _, f in p.outbound.pop_batch(10**9):
        if isinstance(f, str):
            texts.append(json.loads(f))
        else:
            frames.append(f)
    return texts, frames


def events(robot: Peer, core: RelayCore, first: int, n: int, topic: str = "/husky1/events",
           no_drop: bool = True) -> None:
    for i in range(first, first + n):
        core.on_binary(robot, string_frame(topic, f"e{i}", no_drop=no_drop, seq=i))


def stored(core: RelayCore) -> dict[tuple[tuple[str, ...], str], tuple[str, ...]]:
    core.sessions.flush()  # the server does this about once a second (write-behind)
    return {(s.identities, s.name): s.patterns for s in SessionStore(core.registry.db).load()}


def test_session_names_are_checked() -> None:
    for good in ("husky1", "alice@example.com", "ops-console_2", "host:8080", "a" * 64):
        assert check_session_name(good) == good
    for bad in ("", "a" * 65, "-x", "with space", "a/b", "é", None, 3, ["x"]):
        with pytest.raises(BadSessionName, match="bad session name"):
            check_session_name(bad)


@pytest.mark.parametrize("name", ["bad name", "x" * 65, "a,b"])
def test_bad_session_header_closes_4400_with_a_reason(name: str) -> None:
    core = make_core()
    p = authed_peer(core, token=ALICE_TOKEN, session=name)
    texts, _ = drain(p)
    assert texts[-1]["type"] == "error" and texts[-1]["code"] == "bad_session"
    assert closes(p) and closes(p)[0][0] == 4400 and "bad session name" in closes(p)[0][1]
    assert len(core.sessions) == 0 and core.metrics.closes == {4400: 1}


def test_token_frame_names_a_session_only_before_subscribing() -> None:
    core = make_core()
    p = raw_peer(core)
    core.on_text(p, json.dumps({"token": ALICE_TOKEN, "session": "browser-1"}))
    assert p.session is not None and p.session.key == (("alice",), "browser-1")
    late = authed_peer(core, address="127.0.0.2")
    core.on_binary(late, encode_subscription("/husky1/goal_pose"))
    core.on_text(late, json.dumps({"token": ALICE_TOKEN, "session": "too-late"}))
    assert closes(late) == [(4400, "name the session once, before subscribing")]
    odd = raw_peer(core)
    core.on_text(odd, json.dumps({"token": ALICE_TOKEN, "session": 7}))
    assert odd.session is None and closes(odd) == [(4400, "the session name must be a string")]
    header = raw_peer(core, session="from-header")  # the header names it; the frame agrees
    core.on_text(header, json.dumps({"token": ALICE_TOKEN, "session": "from-header"}))
    assert header.session is not None and not closes(header)


def test_subscriptions_persist_and_clean_end_removes_the_session(tmp_path: Path) -> None:
    core = make_core(tmp_path / "fleet.db")
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    for pattern in ("/husky1/.*", "/husky2/events", "/husky1/.*"):  # a duplicate: no-op
        core.on_binary(alice, encode_subscription(pattern))
    assert stored(core) == {(("alice",), "console"): ("/husky1/.*", "/husky2/events")}
    core.on_binary(alice, encode_subscription("/husky2/events", subscribe=False))
    assert stored(core) == {(("alice",), "console"): ("/husky1/.*",)}
    # What RobotLink.stop() does: unsubscribe everything, then close.
    core.on_binary(alice, encode_subscription("/husky1/.*", subscribe=False))
    core.close_peer(alice)
    assert stored(core) == {} and len(core.sessions) == 0
    robot = authed_peer(core, address="127.0.0.2")
    events(robot, core, 0, 3)
    assert not core.sessions.has_offline


def test_a_session_without_subscriptions_leaves_nothing_behind() -> None:
    core = make_core()
    core.close_peer(authed_peer(core, token=ALICE_TOKEN, session="idle"))
    assert len(core.sessions) == 0 and core.sessions.offline_count == 0


def test_offline_mailbox_then_resume_delivers_first_in_order(tmp_path: Path) -> None:
    core = make_core(tmp_path / "fleet.db")
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    robot = authed_peer(core, address="127.0.0.2")
    core.close_peer(alice)
    assert core.sessions.offline_count == 1
    events(robot, core, 0, 5)
    core.on_binary(robot, string_frame("/husky1/scan", "droppable"))  # not mailboxed
    (session,) = core.sessions
    assert [decode_text(f) for _, f in session.mailbox.frames] == [f"e{i}" for i in range(5)]
    again = authed_peer(core, token=ALICE_TOKEN, session="console")
    assert core.sessions.offline_count == 0 and not core.sessions.has_offline
    events(robot, core, 5, 2)  # live frames after the attach queue behind the mailbox
    texts, frames = drain(again)
    assert [t["type"] for t in texts] == ["welcome", "session", "subscribed"]
    assert texts[1] == {"type": "session", "name": "console", "resumed": True,
                        "mailbox_frames": 5, "subscriptions": ["/husky1/.*"]}
    assert [decode_text(f) for f in frames] == [f"e{i}" for i in range(7)]
    # The client's own resubscribe is harmless: acknowledged, nothing stored twice.
    core.on_binary(again, encode_subscription("/husky1/.*"))
    assert core.subs.patterns(again) == ["/husky1/.*"]
    assert stored(core) == {(("alice",), "console"): ("/husky1/.*",)}


def test_mailbox_takes_only_what_the_identity_may_receive() -> None:
    core = make_core()
    bob = authed_peer(core, token=BOB_TOKEN, session="viewer")  # bob receives /husky1/.* only
    core.on_binary(bob, encode_subscription(".*"))
    core.close_peer(bob)
    alice = authed_peer(core, token=ALICE_TOKEN)  # alice may send anything
    for topic in ("/husky1/events", "/husky2/events", "/husky1/log"):
        core.on_binary(alice, string_frame(topic, topic, no_drop=True))
    (session,) = core.sessions
    assert [t for t, _ in session.mailbox.frames] == ["/husky1/events", "/husky1/log"]


def test_sessions_are_per_identity_and_name() -> None:
    core = make_core()
    for token, name in ((ALICE_TOKEN, "x"), (BOB_TOKEN, "x"), (ALICE_TOKEN, "y")):
        p = authed_peer(core, token=token, session=name)
        core.on_binary(p, encode_subscription("/husky1/events"))
        core.close_peer(p)
    both = authed_peer(core, address="127.0.0.2", token=ALICE_TOKEN, session="x")
    assert both.session is not None and both.session.key == (("alice", "husky1"), "x")
    assert {s.key for s in core.sessions} == {
        (("alice",), "x"), (("bob",), "x"), (("alice",), "y"), (("alice", "husky1"), "x")}
    robot = authed_peer(core, address="127.0.0.2")
    events(robot, core, 0, 1)
    # Bob's "x" got its frame too: the same name under another identity is another session.
    assert sorted(len(s.mailbox) for s in core.sessions) == [0, 1, 1, 1]


def test_mailbox_overflow_drops_oldest_counted_and_logged_once(
        caplog: pytest.LogCaptureFixture) -> None:
    core = make_core(session_mailbox_messages=3)
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    core.close_peer(alice)
    robot = authed_peer(core, address="127.0.0.2")
    with caplog.at_level(logging.WARNING, logger="fleetctl.server"):
        events(robot, core, 0, 5)
        events(robot, core, 5, 1, topic="/husky1/other")
    (session,) = core.sessions
    assert [decode_text(f) for _, f in session.mailbox.frames] == ["e3", "e4", "e5"]
    assert core.metrics.session_drops == {(METRIC_ID, "/husky1/events"): 3}
    assert sum("mailbox full" in r.message for r in caplog.records) == 1
    text = core.metrics.render(labelled=core.session_gauges())
    assert (f'fleetctl_session_mailbox_drops_total{{session="{METRIC_ID}",'
            'topic="/husky1/events"} 3') in text
    assert f'fleetctl_session_mailbox_frames{{session="{METRIC_ID}"}} 3.0' in text
    assert 'fleetctl_sessions{state="offline"} 1.0' in text


def test_mailbox_byte_bound() -> None:
    dropped: list[str] = []
    box = Mailbox(100, 10, dropped.append)
    box.put("/a", b"12345")
    box.put("/b", b"123456")  # 11 bytes > 10: the oldest goes
    assert [t for t, _ in box.frames] == ["/b"] and dropped == ["/a"]
    box.put("/c", b"x" * 50)  # larger than the bound: an emptied mailbox still takes it
    assert [t for t, _ in box.frames] == ["/c"] and box.nbytes == 50


def test_fragments_of_no_drop_messages_are_mailboxed() -> None:
    core = make_core()
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(alice, encode_subscription("/husky1/events"))
    core.close_peer(alice)
    robot = authed_peer(core, address="127.0.0.2")
    big = string_frame("/husky1/events", "p" * 3000, no_drop=True, seq=1)
    parts = fragments.split(big, topic="/husky1/events", message_id=5,
                            max_fragment_bytes=1024, no_drop=True)
    assert len(parts) > 2
    for part in parts:
        core.on_binary(robot, part)
    (session,) = core.sessions
    assert [f for _, f in session.mailbox.frames] == parts


def test_expiry_drops_the_session_and_counts_its_mailbox(tmp_path: Path) -> None:
    clock = ManualClock()
    core = make_core(tmp_path / "fleet.db", clock, session_expiry_s=60.0)
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    core.close_peer(alice)
    events(authed_peer(core, address="127.0.0.2"), core, 0, 2)
    clock.now_s += 59
    assert core.sessions.expire() == 0
    clock.now_s += 2
    assert core.sessions.expire() == 1
    assert len(core.sessions) == 0 and not core.sessions.has_offline and stored(core) == {}
    assert core.metrics.session_drops == {(METRIC_ID, "/husky1/events"): 2}


def test_restart_loads_sessions_offline_and_rechecks_them(tmp_path: Path) -> None:
    db = tmp_path / "fleet.db"
    core = make_core(db)
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    core.sessions.flush()  # the periodic write-behind ran ...
    core.registry.close()  # ... then the server died with the session online
    conn = sqlite3.connect(str(db))
    SessionStore(conn).save(("ghost",), "gone", ["/husky1/.*"])  # identity no longer mapped
    conn.close()
    again = make_core(db)
    assert [s.key for s in again.sessions] == [(("alice",), "console")]
    assert again.sessions.offline_count == 1
    events(authed_peer(again, address="127.0.0.2"), again, 0, 3)  # the sender comes back first
    resumed = authed_peer(again, token=ALICE_TOKEN, session="console")
    texts, frames = drain(resumed)
    assert texts[1]["resumed"] is True and texts[1]["mailbox_frames"] == 3
    assert [decode_text(f) for f in frames] == ["e0", "e1", "e2"]
    assert stored(again) == {(("alice",), "console"): ("/husky1/.*",)}


def test_takeover_moves_unsent_and_unacked_frames_to_the_new_connection() -> None:
    core = make_core()
    old = authed_peer(core, token=ALICE_TOKEN, session="console")
    core.on_binary(old, encode_subscription("/husky1/events"))
    drain(old)
    robot = authed_peer(core, address="127.0.0.2")
    events(robot, core, 0, 4)
    assert len(old.outbound.pop_batch(1)) == 1  # e0 written, never acknowledged
    new = authed_peer(core, token=ALICE_TOKEN, session="console")
    assert closes(old) == [(4409, "session taken over by a newer connection")]
    assert core.subs.receivers("/husky1/events") == (new,)
    events(robot, core, 4, 1)
    texts, frames = drain(new)
    assert texts[1]["mailbox_frames"] == 4
    assert [decode_text(f) for f in frames] == ["e0", "e1", "e2", "e3", "e4"]
    core.close_peer(old)  # its close arrives later: it no longer owns the session
    assert new.session is not None and core.sessions.offline_count == 0


def test_too_many_sessions_per_identity() -> None:
    core = make_core(max_sessions_per_identity=2)
    for name in ("a", "b"):
        core.on_binary(authed_peer(core, token=ALICE_TOKEN, session=name),
                       encode_subscription("/x"))
    third = authed_peer(core, token=ALICE_TOKEN, session="c")
    assert closes(third) == [(4400, "identity holds 2 sessions already")]
    assert authed_peer(core, token=BOB_TOKEN, session="c").session is not None  # another identity


def test_droppable_relay_path_unchanged_without_sessions() -> None:
    core = make_core()
    alice = authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    robot = authed_peer(core, address="127.0.0.2")
    events(robot, core, 0, 2)
    assert alice.outbound.ack_mark() is None  # no session: no acknowledgement tracking
    assert [decode_text(f) for f in drain(alice)[1]] == ["e0", "e1"]
