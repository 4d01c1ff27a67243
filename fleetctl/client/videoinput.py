"""Camera messages to the arrays :class:`fleetctl.client.video.VideoEncoder` takes.

``sensor_msgs/msg/Image`` (rosbags message objects, so no rclpy here) is viewed in place
when its encoding is one the encoder converts itself; ``sensor_msgs/msg/CompressedImage``
(JPEG, PNG) is decoded with Pillow first. Anything else raises
:class:`~fleetctl.client.video.UnsupportedImage` with a message naming the encoding, which
the client logs once per topic before relaying such messages as they are
(docs/client.md, "Video").
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from fleetctl.client.video import Image, UnsupportedImage

__all__ = ["IMAGE_ENCODINGS", "compressed_image_array", "image_array"]

# ROS image encoding (sensor_msgs/image_encodings.hpp) -> (PyAV pixel format, bytes/pixel).
# yuv422 is UYVY in ROS; PyAV has no UYVY import, so it is reordered to YUYV here.
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    "rgb8": ("rgb24", 3),
    "bgr8": ("bgr24", 3),
    "rgba8": ("rgba", 4),
    "bgra8": ("bgra", 4),
    "mono8": ("gray", 1),
    "8UC1": ("gray", 1),
    "8UC3": ("bgr24", 3),  # OpenCV's default channel order
    "yuv422": ("yuyv422", 2),
    "uyvy": ("yuyv422", 2),
    "yuv422_yuy2": ("yuyv422", 2),
    "yuyv": ("yuyv422", 2),
}
_UYVY = frozenset({"yuv422", "uyvy"})


def image_array(msg: Any) -> tuple[Image, str]:
    """The pixels of a ``sensor_msgs/msg/Image`` and their PyAV pixel format.

    The array is a view of the message's data when the rows need no reordering.

    Args:
        msg: A rosbags ``sensor_msgs/msg/Image`` (``height``, ``width``, ``encoding``,
            ``step``, ``data``).

    Returns:
        ``(array, pixel_format)``: ``H x W x C`` (``H x W`` for mono) uint8.

    Raises:
        UnsupportedImage: An encoding without a lossless 8-bit conversion (16UC1 depth,
            32FC1, bayer patterns, 16-bit colour), or a data size that does not match
            ``height`` x ``step``.
    """
    encoding = str(msg.encoding)
    known = IMAGE_ENCODINGS.get(encoding)
    if known is None:
        raise UnsupportedImage(
            f"encoding {encoding!r} is not sent as video (only "
            f"{', '.join(sorted(IMAGE_ENCODINGS))}: 8-bit colour or grey)")
    pixel_format, channels = known
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(msg.data, dtype=np.uint8)
    row_bytes = width * channels
    if step < row_bytes or data.size < height * step:
        raise UnsupportedImage(
            f"{encoding} image of {width}x{height} px with step {step} needs "
            f"{height * max(step, row_bytes)} bytes, has {data.size}")
    rows = data[:height * step].reshape(height, step)[:, :row_bytes]
    if channels == 1:
        return rows, pixel_format
    pixels = rows.reshape(height, width, channels)
    if encoding in _UYVY:
        if width % 2:
            raise UnsupportedImage(f"{encoding} image with an odd width ({width} px)")
        # U Y0 V Y1 -> Y0 U Y1 V, pairwise.
        pairs = pixels.reshape(height, width // 2, 4)[:, :, [1, 0, 3, 2]]
        return np.ascontiguousarray(pairs).reshape(height, width, 2), pixel_format
    return pixels, pixel_format


def compressed_image_array(msg: Any) -> tuple[Image, str]:
    """Decode a ``sensor_msgs/msg/CompressedImage`` (JPEG, PNG, ...) to RGB.

    Args:
        msg: A rosbags ``sensor_msgs/msg/CompressedImage`` (``format``, ``data``).

    Returns:
        ``(array, "rgb24")``.

    Raises:
        UnsupportedImage: Pillow cannot read it, or it is not an 8-bit image (a 16-bit
            PNG depth image, for example: ``compressedDepth`` has its own header).
    """
    from PIL import Image as PilImage
    from PIL import UnidentifiedImageError

    fmt = str(msg.format)
    if "compressedDepth" in fmt:
        raise UnsupportedImage(f"format {fmt!r} is a depth image, not sent as video")
    try:
        with PilImage.open(io.BytesIO(np.asarray(msg.data, dtype=np.uint8).tobytes())) as img:
            if img.mode not in ("RGB", "RGBA", "L", "P", "CMYK", "YCbCr", "LA"):
                raise UnsupportedImage(f"format {fmt!r}: a {img.mode} image is not 8-bit "
                                       "colour or grey")
            rgb = np.asarray(img.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise UnsupportedImage(f"format {fmt!r}: cannot decode the image: {exc}") from exc
    return rgb, "rgb24"
