"""Unit tests of camera message -> encoder input conversion (rosbags messages, no ROS)."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pytest
from PIL import Image as PilImage

from fleetctl.client.video import UnsupportedImage, VideoDecoder, VideoEncoder
from fleetctl.client.videoinput import compressed_image_array, image_array
from fleetctl.wire.registry import TypeRegistry

TYPES = TypeRegistry.default().typestore.types
RNG = np.random.default_rng(3)
RGB = RNG.integers(0, 256, (6, 8, 3), dtype=np.uint8)


def image(encoding: str, pixels: np.ndarray, *, step: int | None = None,
          width: int | None = None) -> Any:
    height = pixels.shape[0]
    row = pixels.reshape(height, -1)
    step = step or row.shape[1]
    data = np.zeros((height, step), np.uint8)
    data[:, :row.shape[1]] = row
    header = TYPES["std_msgs/msg/Header"](
        stamp=TYPES["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
    return TYPES["sensor_msgs/msg/Image"](
        header=header, height=height, width=width or pixels.shape[1], encoding=encoding,
        is_bigendian=0, step=step, data=data.reshape(-1))


def compressed(fmt: str, data: bytes) -> Any:
    header = TYPES["std_msgs/msg/Header"](
        stamp=TYPES["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
    return TYPES["sensor_msgs/msg/CompressedImage"](
        header=header, format=fmt, data=np.frombuffer(data, np.uint8))


@pytest.mark.parametrize("encoding, pixels, fmt", [
    ("rgb8", RGB, "rgb24"),
    ("bgr8", RGB[:, :, ::-1], "bgr24"),
    ("rgba8", np.dstack([RGB, RGB[:, :, :1]]), "rgba"),
    ("bgra8", np.dstack([RGB[:, :, ::-1], RGB[:, :, :1]]), "bgra"),
    ("mono8", RGB[:, :, 0], "gray"),
])
def test_8bit_encodings_are_viewed_as_they_are(encoding: str, pixels: np.ndarray,
                                               fmt: str) -> None:
    array, pixel_format = image_array(image(encoding, np.ascontiguousarray(pixels)))
    assert pixel_format == fmt
    assert np.array_equal(array, pixels)


def test_padded_rows_are_cut_to_the_width() -> None:
    array, _ = image_array(image("rgb8", RGB, step=32))  # 24 bytes of pixels + 8 of padding
    assert np.array_equal(array, RGB)


def test_uyvy_is_reordered_to_yuyv() -> None:
    # Two pixels: U Y0 V Y1 = 10 20 30 40 -> Y0 U Y1 V = 20 10 40 30.
    uyvy = np.tile(np.array([10, 20, 30, 40], np.uint8), (2, 2)).reshape(2, 4, 2)
    array, pixel_format = image_array(image("yuv422", uyvy))
    assert pixel_format == "yuyv422"
    assert array.reshape(-1)[:4].tolist() == [20, 10, 40, 30]
    yuyv, _ = image_array(image("yuv422_yuy2", uyvy))
    assert yuyv.reshape(-1)[:4].tolist() == [10, 20, 30, 40]


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1", "bayer_rggb8", "rgb16", "mono16"])
def test_other_encodings_are_refused_with_their_name(encoding: str) -> None:
    with pytest.raises(UnsupportedImage, match=encoding):
        image_array(image(encoding, np.zeros((4, 8), np.uint8)))


def test_short_data_is_refused() -> None:
    msg = image("rgb8", RGB, width=100)  # claims 100 px per row, has 8
    with pytest.raises(UnsupportedImage, match="needs"):
        image_array(msg)


def test_jpeg_and_png_are_decoded_to_rgb() -> None:
    picture = np.repeat(np.repeat(RGB, 8, axis=0), 8, axis=1)  # 48 x 64, blocky
    for fmt, save in (("jpeg", {"format": "JPEG", "quality": 95}), ("png", {"format": "PNG"})):
        buffer = io.BytesIO()
        PilImage.fromarray(picture).save(buffer, **save)
        array, pixel_format = compressed_image_array(compressed(fmt, buffer.getvalue()))
        assert pixel_format == "rgb24" and array.shape == picture.shape
        assert np.abs(array.astype(int) - picture).mean() < (8 if fmt == "jpeg" else 0.01)


def test_bad_compressed_images_are_refused() -> None:
    with pytest.raises(UnsupportedImage, match="cannot decode"):
        compressed_image_array(compressed("jpeg", b"not a jpeg"))
    with pytest.raises(UnsupportedImage, match="depth"):
        compressed_image_array(compressed("16UC1; compressedDepth png", b"\x00" * 16))
    buffer = io.BytesIO()
    PilImage.fromarray(np.zeros((4, 4), np.uint16)).save(buffer, format="PNG")
    with pytest.raises(UnsupportedImage, match="not 8-bit"):
        compressed_image_array(compressed("png", buffer.getvalue()))


def test_yuyv_and_mono_images_encode_to_the_right_picture() -> None:
    grey = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))
    array, fmt = image_array(image("mono8", grey))
    decoded = VideoDecoder("h264").decode(
        VideoEncoder("h264", 64, 48, bitrate_bps=2_000_000).encode(array, 0.0,
                                                                  pixel_format=fmt)[0].data)
    assert decoded is not None
    assert np.abs(decoded[:, :, 1].astype(int) - grey).mean() < 4
    # Flat mid-grey as YUYV: Y 128, U = V = 128.
    yuyv = np.full((48, 64, 2), 128, np.uint8)
    array, fmt = image_array(image("yuv422_yuy2", yuyv))
    decoded = VideoDecoder("h264").decode(
        VideoEncoder("h264", 64, 48).encode(array, 0.0, pixel_format=fmt)[0].data)
    assert decoded is not None and abs(float(decoded.mean()) - 128) < 6
