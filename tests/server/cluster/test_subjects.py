"""Topic -> subject mapping, pattern interest and its cover (no NATS needed)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from fleetctl.server.cluster.interest import Interest
from fleetctl.server.cluster.subjects import (
    cover,
    escape_token,
    literal_prefix,
    pattern_subject,
    subject_matches,
    topic_subject,
)
from fleetctl.server.regex import compile_full

P = "fleetctl"


def test_topic_subjects() -> None:
    assert topic_subject(P, "/husky1/status") == "fleetctl.husky1.status"
    assert topic_subject(P, "/a.b/*/>") == "fleetctl.a~2Eb.~2A.~3E"
    assert topic_subject(P, "/a//b/") == "fleetctl.a.~.b.~"
    assert topic_subject(P, "/with space/~x") == "fleetctl.with~20space.~7Ex"
    assert topic_subject(P, "/é") == "fleetctl.~C3~A9"
    assert topic_subject(P, "relative/x") == "fleetctl.~~.relative.x"
    assert escape_token("") == "~"


@given(st.text(max_size=40))
def test_subjects_are_valid_and_one_to_one(topic: str) -> None:
    subject = topic_subject(P, topic)
    tokens = subject.split(".")
    assert all(tokens) and not any(c in subject for c in " \t\r\n*>")
    assert all(t not in ("*", ">") for t in tokens)
    assert _unescape(subject) == topic


def _unescape(subject: str) -> str:
    tokens = subject.split(".")[1:]
    relative = tokens[0] == "~~"
    segments = [_token(t) for t in (tokens[1:] if relative else tokens)]
    return "/".join(segments) if relative else "/" + "/".join(segments)


def _token(token: str) -> str:
    if token == "~":
        return ""
    out, i = bytearray(), 0
    while i < len(token):
        if token[i] == "~":
            out.append(int(token[i + 1 : i + 3], 16))
            i += 3
        else:
            out += token[i].encode()
            i += 1
    return out.decode("utf-8", "surrogatepass")


def test_literal_prefix() -> None:
    assert literal_prefix("/husky1/.*") == ("/husky1/", False)
    assert literal_prefix("/husky1/cam?") == ("/husky1/ca", False)
    assert literal_prefix("/a/b\\.c") == ("/a/b.c", True)
    assert literal_prefix("/a/b\\.?c") == ("/a/b", False)
    assert literal_prefix("/a/\\d+") == ("/a/", False)
    assert literal_prefix(".*") == ("", False)


def test_pattern_subjects() -> None:
    def subject(pattern: str) -> str:
        return pattern_subject(P, pattern, compile_full(pattern).literal)

    assert subject("/husky1/status") == "fleetctl.husky1.status"
    assert subject("/husky1/.*") == "fleetctl.husky1.>"
    assert subject("/husky1/cam/(a|b)") == "fleetctl.>"  # alternation: no safe prefix
    assert subject("/husky1.*") == "fleetctl.>"  # the segment may go on: /husky10/x
    assert subject("/husky1/ca[m]/x") == "fleetctl.husky1.>"
    assert subject(".*") == "fleetctl.>"
    # The page subscribes to each robot's status with re-escaped names.
    assert subject("/robot\\.1/status") == "fleetctl.robot~2E1.status"
    assert subject("/robot\\.1/.*") == "fleetctl.robot~2E1.>"


@given(st.lists(st.sampled_from(["a", "b", "x.y"]), min_size=1, max_size=4),
       st.lists(st.sampled_from(["a", "b", "c", "x.y"]), min_size=1, max_size=4))
def test_pattern_subject_covers_every_match(head: list[str], tail: list[str]) -> None:
    pattern = "/" + "/".join(head) + "/.*"
    topic = "/" + "/".join(head + tail)
    compiled = compile_full(pattern)
    assert compiled.matches(topic)
    assert subject_matches(topic_subject(P, topic), pattern_subject(P, pattern, None))


def test_cover_drops_what_a_wider_subject_holds() -> None:
    assert cover({"f.a.>", "f.a.b", "f.a.b.>", "f.a", "f.c.d"}) == {"f.a.>", "f.a", "f.c.d"}
    assert cover({"f.>", "f.a.b"}) == {"f.>"}
    assert cover(set()) == frozenset()


def test_interest_follows_subscriptions() -> None:
    interest = Interest(P)
    assert interest.follow("/husky1/status", 1)
    assert interest.wanted == {"fleetctl.husky1.status"}
    assert not interest.follow("/husky1/status", 1)  # a second holder: nothing new
    assert interest.follow("/husky1/.*", 1)
    assert interest.wanted == {"fleetctl.husky1.>"}
    assert interest.follow("/husky1/.*", -1)
    assert interest.wanted == {"fleetctl.husky1.status"}
    assert not interest.follow("/husky1/status", -1)
    assert interest.follow("/husky1/status", -1)
    assert interest.wanted == frozenset()
