"""Unit tests of the video hook (worker thread, keyframes, link feedback) with fake link
callables; real rosbags messages, real wire codec, real PyAV. No rclpy needed."""

from __future__ import annotations

import dataclasses
import functools
import io
import logging
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from PIL import Image as PilImage

from fleetctl.client.config import parse_client_config
from fleetctl.client.ros import videotopic
from fleetctl.client.ros.videotopic import VideoTopic
from fleetctl.client.scheduler import TopicFeedback
from fleetctl.client.syntheticcamera import CameraSequence
from fleetctl.client.transport import LinkFeedback
from fleetctl.client.video import VIDEO_TYPE, VideoDecoder
from fleetctl.wire.codec import Codec
from fleetctl.wire.registry import TypeRegistry
from tests.support import wait_for_value

CODEC = Codec(TypeRegistry.default())
TS = CODEC.registry.typestore
CAMERA = CameraSequence(320, 240, seed=2)
DEADLINE_S = 10.0


def spec(type_name: str = "sensor_msgs/msg/Image", **video: Any) -> Any:
    config = parse_client_config({
        "server_url": "ws://127.0.0.1:1/", "robot_name": "r1",
        "publish": [{"topic": "/camera", "type": type_name, "priority": 2,
                     "video": {"codec": "h264", **video}}]}, source="test.yaml")
    return config.publish[0]


def header(index: int) -> Any:
    stamp = TS.types["builtin_interfaces/msg/Time"](sec=1000 + index // 30,
                                                   nanosec=(index % 30) * 33_333_333)
    return TS.types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera_optical")


def image_cdr(index: int, encoding: str = "rgb8") -> bytes:
    pixels = CAMERA.frame(index)
    if encoding == "16UC1":
        pixels = np.zeros((240, 320, 2), np.uint8)
    msg = TS.types["sensor_msgs/msg/Image"](
        header=header(index), height=240, width=320, encoding=encoding, is_bigendian=0,
        step=pixels.shape[1] * pixels.shape[2], data=pixels.reshape(-1))
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def jpeg_cdr(index: int) -> bytes:
    buffer = io.BytesIO()
    PilImage.fromarray(CAMERA.frame(index)).save(buffer, format="JPEG", quality=90)
    msg = TS.types["sensor_msgs/msg/CompressedImage"](
        header=header(index), format="jpeg", data=np.frombuffer(buffer.getvalue(), np.uint8))
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


class FakeLink:
    """The callables the bridge gives a VideoTopic, recording what they get."""

    def __init__(self) -> None:
        self.frames: list[tuple[bytes, bool]] = []
        self.relayed: list[Any] = []
        self.seq = 0
        self.feedback = LinkFeedback(1, TopicFeedback(0.0, 0, 0, False, 0))
        self.now = 0.0
        self.gate: threading.Event | None = None
        self.in_send = threading.Event()

    def send(self, frame: bytes, keyframe: bool) -> None:
        self.in_send.set()
        if self.gate is not None:
            assert self.gate.wait(DEADLINE_S)
        self.frames.append((frame, keyframe))

    def relay(self, msg: Any) -> bool:
        self.relayed.append(msg)
        return True

    def next_seq(self, topic: str) -> int:
        self.seq += 1
        return self.seq

    def topic(self, **changes: Any) -> None:
        self.feedback = dataclasses.replace(
            self.feedback, topic=dataclasses.replace(self.feedback.topic, **changes))


@pytest.fixture
def link() -> FakeLink:
    return FakeLink()


@pytest.fixture
def video(link: FakeLink) -> Iterator[VideoTopic]:
    topic = make(link, spec())
    yield topic
    topic.close()


def make(link: FakeLink, entry: Any) -> VideoTopic:
    return VideoTopic(entry, typestore=TS, codec=CODEC, send=link.send, relay=link.relay,
                      next_seq=link.next_seq, feedback=lambda _topic: link.feedback,
                      clock=lambda: link.now)


def push(video: VideoTopic, link: FakeLink, cdr: bytes) -> tuple[bytes, bool]:
    """Offer one message and wait until its frame was sent."""
    before = len(link.frames)
    assert video.offer(cdr)
    wait_for_value(lambda: len(link.frames) > before, DEADLINE_S)
    return link.frames[-1]


def test_images_become_decodable_compressed_video_frames(video: VideoTopic,
                                                         link: FakeLink) -> None:
    decoder = VideoDecoder("h264")
    for i in range(5):
        frame, keyframe = push(video, link, image_cdr(i))
        meta, msg = CODEC.decode(frame)
        assert (meta.type, meta.topic, meta.seq, meta.no_drop) == (VIDEO_TYPE, "/r1/camera",
                                                                    i + 1, False)
        assert keyframe is (i == 0)
        assert msg.format == "h264" and msg.frame_id == "camera_optical"
        assert (msg.timestamp.sec, msg.timestamp.nanosec) == (1000, i * 33_333_333)
        picture = decoder.decode(bytes(msg.data), meta.seq)
        assert picture is not None and picture.shape == (240, 320, 3)
    assert video.stats.frames_sent == 5 and video.stats.keyframes_sent == 1
    assert video.stats.bitrate_bps == 1_000_000


def test_compressed_images_are_decoded_then_encoded(link: FakeLink) -> None:
    video = make(link, spec("sensor_msgs/msg/CompressedImage"))
    try:
        frame, keyframe = push(video, link, jpeg_cdr(0))
        assert keyframe
        _, msg = CODEC.decode(frame)
        assert VideoDecoder("h264").decode(bytes(msg.data)) is not None
    finally:
        video.close()


def test_keyframe_on_request_on_drop_and_on_reconnect(video: VideoTopic,
                                                      link: FakeLink) -> None:
    assert push(video, link, image_cdr(0))[1]
    assert not push(video, link, image_cdr(1))[1]
    video.request_keyframe()
    assert push(video, link, image_cdr(2))[1], "a viewer asked"
    assert not push(video, link, image_cdr(3))[1]
    link.topic(dropped=1)
    assert push(video, link, image_cdr(4))[1], "the link dropped a frame of the topic"
    assert not push(video, link, image_cdr(5))[1]
    link.feedback = dataclasses.replace(link.feedback, connects=2)
    assert push(video, link, image_cdr(6))[1], "the link reconnected"
    assert not push(video, link, image_cdr(7))[1]
    assert video.stats.keyframe_requests == 1 and video.stats.keyframes_sent == 4


def test_frames_wait_for_the_link_instead_of_being_dropped_by_it(video: VideoTopic,
                                                                 link: FakeLink) -> None:
    push(video, link, image_cdr(0))
    link.topic(busy=True)
    assert video.offer(image_cdr(1))
    wait_for_value(lambda: video.stats.skipped_busy == 1, DEADLINE_S)
    link.topic(busy=False)
    assert not push(video, link, image_cdr(2))[1], "skipped before the encoder: no break"
    assert video.stats.frames_sent == 2


def test_the_slot_keeps_only_the_newest_message(video: VideoTopic, link: FakeLink) -> None:
    link.gate = threading.Event()
    assert video.offer(image_cdr(0))
    assert link.in_send.wait(DEADLINE_S)  # the worker holds frame 0 in send()
    for i in (1, 2, 3):
        assert video.offer(image_cdr(i))
    link.gate.set()
    wait_for_value(lambda: len(link.frames) == 2, DEADLINE_S)
    assert video.stats.replaced == 2
    _, msg = CODEC.decode(link.frames[1][0])
    assert msg.timestamp.nanosec == 3 * 33_333_333


def test_the_bitrate_starts_from_the_link_estimate_and_follows_it(video: VideoTopic,
                                                                  link: FakeLink) -> None:
    link.topic(link_rate_Bps=100_000.0)  # 50 % of 800 kbit/s
    push(video, link, image_cdr(0))
    assert video.stats.bitrate_bps == 400_000
    link.now = 1.5
    link.topic(dropped=1, link_rate_Bps=40_000.0)
    assert push(video, link, image_cdr(1))[1]  # the drop: a keyframe, and 50 % of 320
    assert video.stats.bitrate_bps == 160_000
    link.now = 3.0
    link.topic(link_rate_Bps=1.0)  # an idle link's estimate does not pull it down
    push(video, link, image_cdr(2))
    assert video.stats.bitrate_bps == 184_000


def test_unsupported_encodings_are_relayed_unchanged_with_one_log_line(
        video: VideoTopic, link: FakeLink, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="fleetctl.client.ros.videotopic")
    for i in range(3):
        assert video.offer(image_cdr(i, "16UC1"))
        wait_for_value(functools.partial(lambda n: len(link.relayed) == n, i + 1), DEADLINE_S)
    assert video.stats.relayed == 3 and link.frames == []
    assert link.relayed[0].encoding == "16UC1"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "/camera" in lines[0] and "16UC1" in lines[0]
    assert "relaying these messages unchanged as sensor_msgs/msg/Image" in lines[0]
    assert push(video, link, image_cdr(3))[1], "a supported image is video again"


def test_images_too_small_for_video_are_relayed_unchanged(
        video: VideoTopic, link: FakeLink, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="fleetctl.client.ros.videotopic")
    msg = TS.types["sensor_msgs/msg/Image"](
        header=header(0), height=8, width=8, encoding="rgb8", is_bigendian=0, step=24,
        data=np.zeros(8 * 24, np.uint8))
    assert video.offer(bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/Image")))
    wait_for_value(lambda: len(link.relayed) == 1, DEADLINE_S)
    assert video.stats.relayed == 1 and video.stats.errors == 0 and link.frames == []
    assert any("8x8" in r.getMessage() for r in caplog.records)


def test_a_codec_the_encoder_lacks_falls_back_to_relaying(
        link: FakeLink, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(videotopic, "codec_problem",
                        lambda codec: f"PyAV's FFmpeg has no encoder for {codec}")
    caplog.set_level(logging.WARNING, logger="fleetctl.client.ros.videotopic")
    video = make(link, spec(codec="av1"))
    assert video.offer(image_cdr(0)) is False
    video.close()
    assert [r.getMessage() for r in caplog.records] == [
        "video: /camera: PyAV's FFmpeg has no encoder for av1: relaying "
        "sensor_msgs/msg/Image messages unchanged instead"]


def test_an_undecodable_message_is_counted_and_the_topic_goes_on(
        video: VideoTopic, link: FakeLink) -> None:
    assert video.offer(b"\x00\x01\x00\x00garbage")
    wait_for_value(lambda: video.stats.errors == 1, DEADLINE_S)
    assert push(video, link, image_cdr(0))[1]
