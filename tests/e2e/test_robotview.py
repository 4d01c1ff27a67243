"""The robot's view of a window: two stats snapshots in, one note out."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from fleetctl.deploy.dockercli import Completed
from fleetctl.e2e import robotview


def _snapshot(scan: tuple[int, int], pose: tuple[int, int], *, rate: float = 1.5e6,
              whole: int = 9000, deflate_all: bool = False, switches: int = 0) -> dict[str, Any]:
    return {
        "link_rate_Bps": rate, "whole_frame_bytes": whole, "window_bytes": 8192,
        "min_rtt_ms": 0.84,
        "topics": {"/robot1/scan": {"sent": scan[0], "sent_frames": scan[1]},
                   "/robot1/pose": {"sent": pose[0], "sent_frames": pose[1]}},
        "uplink_deflate": {"all_messages": deflate_all, "switches": switches,
                           "wire_share": 0.53},
    }


def test_the_window_is_the_difference_and_the_limits_are_the_end() -> None:
    view = robotview.window_view(
        _snapshot((10, 12), (20, 20)),
        _snapshot((40, 102), (80, 80), rate=1.0e6, whole=6000, deflate_all=True, switches=1))
    assert view.topics["/robot1/scan"] == robotview.TopicFrames(30, 90)
    assert view.topics["/robot1/pose"] == robotview.TopicFrames(60, 60)
    assert (view.link_rate_Bps, view.whole_frame_bytes, view.deflate_all,
            view.deflate_switches) == (1.0e6, 6000, True, 1)


def test_a_topic_new_in_the_window_counts_from_zero() -> None:
    start = _snapshot((0, 0), (0, 0))
    del start["topics"]["/robot1/scan"]
    view = robotview.window_view(start, _snapshot((5, 15), (0, 0)))
    assert view.topics["/robot1/scan"] == robotview.TopicFrames(5, 15)


def test_the_note_says_what_the_robot_did() -> None:
    view = robotview.window_view(
        _snapshot((0, 0), (0, 0)),
        _snapshot((30, 90), (60, 60), rate=1.0e6, whole=6000, deflate_all=True, switches=1))
    note = robotview.view_note("fleetctl robot at 1 consumer(s)", view)
    assert note == (
        "fleetctl robot at 1 consumer(s): link rate 8.0 Mbit/s of frame bytes, frames up to "
        "6000 B sent whole, window 8192 B, min RTT 0.84 ms; deflating every message "
        "(slow-link rule), wire share 0.53, 1 switch(es) in the window; /robot1/pose 60 "
        "messages in 60 frames, /robot1/scan 30 messages in 90 frames")


def test_no_view_is_said_not_guessed() -> None:
    assert "gave no stats" in robotview.view_note("fleetctl robot", None)
    # Either snapshot missing: no view; an empty start counts from the connect.
    assert "gave no stats" in robotview.window_note("r", None, _snapshot((1, 1), (1, 1)))
    assert "gave no stats" in robotview.window_note("r", _snapshot((1, 1), (1, 1)), None)
    assert "/robot1/scan 5 messages in 15 frames" in robotview.window_note(
        "r", {}, _snapshot((5, 15), (0, 0)))


@dataclass
class _Robot:
    """A container whose client logs a stats line when signalled (or not)."""

    answers: bool = True
    running: bool = True
    line: str = ""
    signals: list[list[str]] = field(default_factory=list)
    output: str = "robot started\n"
    log_reads: int = 0

    def exec(self, container: str, argv: Sequence[str], *, user: str = "root") -> Completed:
        self.signals.append(list(argv))
        if self.answers and self.running:
            self.output += self.line
        return Completed(tuple(argv), 0 if self.running else 1, "", "")

    def logs(self, container: str) -> str:
        self.log_reads += 1
        return self.output


def test_reading_takes_the_line_written_after_the_signal() -> None:
    robot = _Robot(output="stats: {\"old\": true}\n",
                   line="stats: " + json.dumps(_snapshot((1, 1), (2, 2))) + "\n")
    stats = robotview.read_stats(robot, "robot")
    assert stats is not None and stats["topics"]["/robot1/scan"]["sent"] == 1
    assert robot.signals == [["pkill", "-USR1", "-f", "fleetctl client"]]


def test_a_robot_that_does_not_answer_gives_none_at_the_deadline() -> None:
    assert robotview.read_stats(_Robot(answers=False), "robot", timeout_s=0.3) is None


def test_a_line_that_is_not_json_gives_none() -> None:
    assert robotview.read_stats(_Robot(line="stats: {not json\n"), "robot") is None


def test_a_robot_whose_client_exited_gives_none_without_waiting() -> None:
    robot = _Robot(running=False)
    assert robotview.read_stats(robot, "robot", timeout_s=30.0) is None
    assert robot.log_reads == 1  # the count before the signal; no polling after it failed
