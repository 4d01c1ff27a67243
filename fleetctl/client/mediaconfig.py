"""The media keys of ``client.yaml``: a camera entry's ``video``, a cloud entry's
``viewer_cloud`` and the top-level ``tf`` (docs/client.md), with their readers.

:mod:`fleetctl.client.config` re-exports every public name: import them from there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetctl.client.configfields import Ctx, integer, mapping, number, sub_mapping

_VIDEO_KEYS = frozenset(
    {"codec", "max_bitrate_kbps", "min_bitrate_kbps", "keyframe_interval_s"}
)
# Codecs PyAV's wheels encode and Chromium's WebCodecs decodes (docs/client.md).
VIDEO_CODECS = ("h264", "vp8", "vp9", "av1")
VIDEO_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_VIEWER_CLOUD_KEYS = frozenset({"resolution_m"})
VIEWER_CLOUD_TYPES = ("sensor_msgs/msg/PointCloud2",)
_TF_KEYS = frozenset({"translation_delta_m", "rotation_delta_rad", "max_rate_hz"})


@dataclass(frozen=True)
class VideoSpec:
    """A camera topic sent as ``foxglove_msgs/msg/CompressedVideo``.

    Attributes:
        codec: ``h264``, ``vp8``, ``vp9`` or ``av1``.
        max_bitrate_kbps: Upper bound of the encoder's bitrate (kbit/s).
        min_bitrate_kbps: Lower bound the bitrate never goes under when the link is slow
            (kbit/s).
        keyframe_interval_s: Seconds between periodic keyframes.
    """

    codec: str = "h264"
    max_bitrate_kbps: int = 1000
    min_bitrate_kbps: int = 100
    keyframe_interval_s: float = 2.0


@dataclass(frozen=True)
class ViewerCloudSpec:
    """A viewer encoding of a ``PointCloud2`` sent beside the full cloud.

    Attributes:
        resolution_m: Voxel edge in metres the points are quantized to.
    """

    resolution_m: float = 0.01


@dataclass(frozen=True)
class TfSpec:
    """The TF republisher (tf2_web_republisher semantics, docs/client.md).

    Attributes:
        translation_delta_m: A transform is re-sent when it moved more than this (metres).
        rotation_delta_rad: ... or turned more than this (radians).
        max_rate_hz: Upper bound of ``/<robot>/tf`` messages per second.
    """

    translation_delta_m: float = 0.01
    rotation_delta_rad: float = 0.01
    max_rate_hz: float = 10.0


def video_spec(ctx: Ctx, value: object, where: str, type_name: str) -> VideoSpec | None:
    """The ``video`` key of publish entry *where* of type *type_name*; None when absent.

    Raises:
        ConfigError: not an image type, or a field is invalid (named ``<where>: video: ...``).
    """
    if value is None:
        return None
    if type_name not in VIDEO_TYPES:
        raise ctx.error(where, "video", f"only for {' or '.join(VIDEO_TYPES)}, "
                                        f"not {type_name}")
    inner = f"{where}: video"
    entry = sub_mapping(ctx, value, where, "video", _VIDEO_KEYS)
    d = VideoSpec()
    codec = entry.get("codec", d.codec)
    if codec not in VIDEO_CODECS:
        raise ctx.error(inner, "codec", f"must be one of {', '.join(VIDEO_CODECS)}, "
                                        f"got {codec!r}")
    hi = integer(ctx, entry, inner, "max_bitrate_kbps", d.max_bitrate_kbps, 1, 1_000_000)
    lo = integer(ctx, entry, inner, "min_bitrate_kbps", d.min_bitrate_kbps, 1, 1_000_000)
    if lo > hi:
        raise ctx.error(inner, "min_bitrate_kbps", f"must be <= max_bitrate_kbps ({hi}), "
                                                   f"got {lo}")
    interval = number(ctx, entry, inner, "keyframe_interval_s", d.keyframe_interval_s,
                       lambda v: v > 0, "> 0")
    assert interval is not None
    return VideoSpec(codec=str(codec), max_bitrate_kbps=hi, min_bitrate_kbps=lo,
                     keyframe_interval_s=interval)


def viewer_cloud_spec(
    ctx: Ctx, value: object, where: str, type_name: str
) -> ViewerCloudSpec | None:
    """The ``viewer_cloud`` key of publish entry *where*; None when absent.

    Raises:
        ConfigError: not a PointCloud2 entry, or ``resolution_m`` outside 0.001..1 m.
    """
    if value is None:
        return None
    if type_name not in VIEWER_CLOUD_TYPES:
        raise ctx.error(where, "viewer_cloud", f"only for {VIEWER_CLOUD_TYPES[0]}, "
                                               f"not {type_name}")
    entry = sub_mapping(ctx, value, where, "viewer_cloud", _VIEWER_CLOUD_KEYS)
    # int16 voxel indices: 1 mm keeps +-32 m, 1 m is coarser than any viewer wants.
    res = number(ctx, entry, f"{where}: viewer_cloud", "resolution_m",
                  ViewerCloudSpec().resolution_m, lambda v: 0.001 <= v <= 1.0,
                  "between 0.001 and 1")
    assert res is not None
    return ViewerCloudSpec(resolution_m=res)


def tf_spec(ctx: Ctx, value: object) -> TfSpec | None:
    """The top-level ``tf`` section; None when absent or null (``tf: {}``: the defaults).

    Raises:
        ConfigError: a field is invalid (named ``tf: ...``).
    """
    if value is None:
        return None
    if isinstance(value, bool):  # `tf: true` reads naturally but is not the syntax
        raise ctx.error("", "tf", f"must be a mapping, got {str(value).lower()} "
                        "(tf: {} turns TF on with the defaults; leave it out for no TF)")
    entry = mapping(ctx, value, "tf", "entry", _TF_KEYS)
    d = TfSpec()
    trans = number(ctx, entry, "tf", "translation_delta_m", d.translation_delta_m,
                    lambda v: v >= 0, ">= 0")
    rot = number(ctx, entry, "tf", "rotation_delta_rad", d.rotation_delta_rad,
                  lambda v: 0 <= v <= math.pi, "between 0 and pi")
    rate = number(ctx, entry, "tf", "max_rate_hz", d.max_rate_hz, lambda v: 0 < v <= 1000,
                   "> 0 and <= 1000")
    assert trans is not None and rot is not None and rate is not None
    return TfSpec(translation_delta_m=trans, rotation_delta_rad=rot, max_rate_hz=rate)


def tf_remote_topics(robot_name: str) -> tuple[str, str]:
    """The remote topics of the TF republisher: ``/<robot>/tf`` and ``/<robot>/tf_static``."""
    return f"/{robot_name}/tf", f"/{robot_name}/tf_static"
