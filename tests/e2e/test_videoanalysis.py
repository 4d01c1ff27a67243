"""The video checks of the e2e scenarios, on hand-made frame records."""

from __future__ import annotations

import math
from dataclasses import replace

from fleetctl.e2e import videoanalysis
from fleetctl.e2e.samples import Sample, dump, load

S = 1_000_000_000


def frame(wire_seq: int, t_s: float, key: bool = False, shown: bool = True,
          size: int = 1000) -> Sample:
    t = int(t_s * S)
    return Sample("/r/cam", wire_seq, t - 5_000_000, t, size, "c0", wire_seq=wire_seq,
                  keyframe=key, shown_ns=t + 1_000_000 if shown else None)


def test_intact_chains_and_a_gap_refused_until_the_keyframe() -> None:
    frames = [frame(1, 0.0, key=True), frame(2, 0.1), frame(3, 0.2),
              frame(6, 0.8, shown=False), frame(7, 0.9, shown=False),
              frame(8, 1.0, key=True), frame(9, 1.1)]
    c = videoanalysis.chain(frames)
    assert c == videoanalysis.Chain(frames=7, keyframes=2, shown=5, gaps=1, broken_shown=0)


def test_a_frame_shown_after_a_gap_is_a_broken_reference() -> None:
    frames = [frame(1, 0.0, key=True), frame(2, 0.1), frame(4, 0.3), frame(5, 0.4)]
    assert videoanalysis.chain(frames).broken_shown == 2
    # Frames shown before any keyframe have no reference either.
    assert videoanalysis.chain([frame(5, 0.0), frame(6, 0.1, key=True)]).broken_shown == 1


def test_arrival_order_not_file_order_decides() -> None:
    frames = [frame(2, 0.1), frame(1, 0.0, key=True)]
    assert videoanalysis.chain(frames).broken_shown == 0


def test_first_shown_after_the_restore() -> None:
    frames = [frame(1, 1.0, key=True), frame(2, 7.0, shown=False), frame(3, 7.4, key=True)]
    assert videoanalysis.first_shown_after_s(frames, 7 * S) == 0.401
    assert math.isinf(videoanalysis.first_shown_after_s(frames[:2], 7 * S))
    # A frame taken before the cut and shown after it is not the live picture.
    old = replace(frame(9, 7.05), publish_time_ns=2 * S)
    assert videoanalysis.first_shown_after_s([old, *frames], 7 * S) == 0.051
    assert videoanalysis.first_shown_after_s([old, *frames], 7 * S, fresh=True) == 0.401


def test_bitrate_line_and_mean() -> None:
    frames = [frame(i, 0.1 * i, size=12_500) for i in range(20)]  # 10 per s: 1 Mbit/s
    xs, ys = videoanalysis.bitrate_line(frames, 0, 2 * S)
    assert xs == [0.5, 1.5] and ys == [1.0, 1.0]
    assert videoanalysis.mean_mbit_s(frames, 0, S) == 1.0


def test_dropout_criteria_fail_without_any_frame_shown() -> None:
    rows, notes = videoanalysis.dropout_criteria("/r/cam", [frame(1, 8.0, shown=False)], 7 * S)
    assert [r["ok"] for r in rows] == [False, False]
    assert "1 frames received" in notes[0]
    rows, _ = videoanalysis.dropout_criteria(
        "/r/cam", [frame(1, 7.2, key=True), frame(2, 7.3)], 7 * S)
    assert [r["ok"] for r in rows] == [True, True]


def test_video_fields_round_trip_and_are_left_out_for_other_topics() -> None:
    plain = Sample("/r/pose", 1, 2, 3, 4, "c0")
    assert "keyframe" not in dump([plain]) and not plain.is_video
    video = frame(3, 1.0, key=True)
    assert list(load(dump([plain, video]))) == [plain, video]
