"""The viewer encoding of a point cloud: ``PointCloud2`` -> ``fleetctl_msgs/msg/ViewerCloud``.

A viewer draws a cloud at screen resolution, so the robot can send it quantized: every
point snapped to a voxel grid of ``resolution_m`` (1 cm by default), one point per occupied
voxel, voxels sorted by their (x, y, z) index and written as planar int16 indices plus
planar 8-bit colours. Sorted planar indices are what makes the result small after deflate
(``fleetctl.wire.compression``, which the page inflates natively): the x plane is long runs
of equal values, the y plane runs within each x, and neighbouring surface voxels repeat
byte patterns. The ``.msg`` comment (``fleetctl/wire/msg/fleetctl_msgs/msg/ViewerCloud.msg``)
is the format; ``fleetctl/webviz/static/js/viewercloud.js`` decodes it; docs/client.md
gives the figures.

Decisions:

- Origin = the cloud's minimum per axis (float32), so indices are 0..32767. A cloud whose
  extent on some axis needs more than 32767 voxels is *coarsened*: its resolution is raised
  just enough for that cloud (the message carries its resolution, viewers need nothing
  else), counted in :attr:`ViewerCloudStats.coarsened`. Every finite point is kept; the
  alternative, dropping far points, would silently cut a long-range lidar's cloud.
- NaN and infinite points (invalid depth pixels of an organized cloud) are dropped, counted.
- The colour of a voxel is that of its first point (in the cloud's order): a mean costs
  more and a 1 cm voxel already blurs texture edges less than a screen pixel does.
- Quantization uses the float32 value of the resolution and the float32 origin, exactly
  what the receiver reads, so a decoded point is within ``resolution * sqrt(3) / 2`` of every
  original point of its voxel.

Pure numpy, no rclpy: the ROS node calls :class:`ViewerClouds` from its publish path.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetctl.client.config import PublishSpec
from fleetctl.wire.codec import default_codec

log = logging.getLogger(__name__)

VIEWER_CLOUD_TYPE = "fleetctl_msgs/msg/ViewerCloud"
VIEWER_SUFFIX = "/viewer"  # the viewer topic is <remote_topic>/viewer (docs/client.md)
MAX_INDEX = 32767  # int16 indices from a per-cloud minimum: 0..32767

# sensor_msgs/msg/PointField datatypes this module reads.
_FLOAT32, _FLOAT64, _UINT32 = 7, 8, 6
_FLOAT_SIZES = {_FLOAT32: 4, _FLOAT64: 8}
_COLOUR_FIELDS = ("rgb", "rgba")


class ViewerCloudError(ValueError):
    """A cloud that cannot be encoded for viewers; the message names the field."""


@dataclass
class ViewerCloudStats:
    """Counters of the viewer encoding (plain ints; read from any thread).

    Attributes:
        clouds: clouds encoded.
        errors: clouds that could not be encoded (no x/y/z, bad layout; logged).
        points_in: points of the encoded clouds (width * height).
        points_nonfinite: of those, dropped because a coordinate was NaN or infinite.
        points_out: voxels sent (one point each).
        coarsened: clouds whose resolution was raised to fit int16 indices.
    """

    clouds: int = 0
    errors: int = 0
    points_in: int = 0
    points_nonfinite: int = 0
    points_out: int = 0
    coarsened: int = 0


def encode(
    msg: Any,
    resolution_m: float,
    *,
    cls: Any = None,
    stats: ViewerCloudStats | None = None,
) -> Any:
    """Encode a ``sensor_msgs/msg/PointCloud2`` for viewers.

    Args:
        msg: A rosbags PointCloud2 (any object with its fields; ``data`` a uint8 buffer).
        resolution_m: Voxel edge in metres (> 0); raised for this cloud when its extent
            needs more than :data:`MAX_INDEX` voxels on an axis.
        cls: The ViewerCloud message class (default: fleetctl's default registry's).
        stats: Counters to update (None: not counted).

    Returns:
        A ``fleetctl_msgs/msg/ViewerCloud`` with the cloud's header; ``rgb`` is empty when
        the cloud has no ``rgb``/``rgba`` field.

    Raises:
        ViewerCloudError: No float32/float64 x, y or z field, or fields/steps that do not
            fit the data (the message says which).
    """
    if not resolution_m > 0:
        raise ViewerCloudError(f"resolution_m must be > 0, got {resolution_m}")
    xyz, rgb = _read_points(msg)
    finite = np.isfinite(xyz[0]) & np.isfinite(xyz[1]) & np.isfinite(xyz[2])
    if stats is not None:
        stats.points_in += xyz.shape[1]
        stats.points_nonfinite += xyz.shape[1] - int(np.count_nonzero(finite))
    if not finite.all():
        # np.compress keeps rows C-contiguous (xyz[:, mask] comes out strided: 10x slower
        # reductions afterwards).
        xyz = np.compress(finite, xyz, axis=1)
        rgb = rgb[finite] if rgb is not None else None
    origin, res, index = _quantize(xyz, float(resolution_m))
    if stats is not None and res > np.float32(resolution_m):
        stats.coarsened += 1
    order = _voxel_order(index)
    out_index = np.take(index, order, axis=1).reshape(-1)
    out_rgb = np.empty(0, np.uint8)
    if rgb is not None:
        out_rgb = np.ascontiguousarray(_unpack_rgb(rgb[order]).T).reshape(-1)
    if stats is not None:
        stats.clouds += 1
        stats.points_out += order.size
    cls = cls if cls is not None else default_codec().registry.get(VIEWER_CLOUD_TYPE).cls
    return cls(msg.header, float(res), float(origin[0]), float(origin[1]), float(origin[2]),
               out_index, out_rgb)


def decode(msg: Any) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.uint8] | None]:
    """The points of a ViewerCloud (the reference decoder; the page has its own in JS).

    Returns:
        ``(xyz, rgb)``: positions, shape (n, 3), metres, in float64 from the message's
        float32 values (voxel centres); colours, shape (n, 3), or None when not sent.

    Raises:
        ViewerCloudError: ``xyz`` or ``rgb`` of the wrong length.
    """
    index = np.asarray(msg.xyz, dtype=np.int16)
    if index.size % 3:
        raise ViewerCloudError(f"xyz has {index.size} values, not a multiple of 3")
    n = index.size // 3
    res = float(np.float32(msg.resolution_m))
    origin = np.array([msg.origin_x, msg.origin_y, msg.origin_z], np.float32).astype(np.float64)
    xyz = origin + (index.reshape(3, n).T.astype(np.float64) + 0.5) * res
    rgb = np.asarray(msg.rgb, dtype=np.uint8)
    if rgb.size == 0:
        return xyz, None
    if rgb.size != 3 * n:
        raise ViewerCloudError(f"rgb has {rgb.size} values for {n} points (3 per point or none)")
    return xyz, np.ascontiguousarray(rgb.reshape(3, n).T)


# --- reading a PointCloud2 -----------------------------------------------------------------


def _read_points(msg: Any) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.uint32] | None]:
    """``(xyz, rgb)``: coordinates, shape (3, n), float64; packed colours (n,) or None."""
    fields = {f.name: f for f in msg.fields}
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        names = ", ".join(f.name for f in msg.fields) or "none"
        raise ViewerCloudError(f"no {'/'.join(missing)} field (fields: {names})")
    width, height = int(msg.width), int(msg.height)
    step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if width * height == 0:
        return np.empty((3, 0), np.float64), None
    if step <= 0:
        raise ViewerCloudError(f"point_step is {step}")
    if height > 1 and row_step < width * step:
        raise ViewerCloudError(f"row_step {row_step} < width {width} * point_step {step}")
    order = ">" if msg.is_bigendian else "<"
    view = _Strided(data, width, height, step, row_step, order)
    xyz = np.empty((3, width * height), np.float64)
    for i, axis in enumerate("xyz"):
        f = fields[axis]
        size = _FLOAT_SIZES.get(int(f.datatype))
        if size is None:
            raise ViewerCloudError(f"field {axis} has datatype {f.datatype}, "
                                   f"not float32 (7) or float64 (8)")
        # One strided pass: byte order and float64 conversion happen in the copy.
        xyz[i].reshape(height, width)[...] = view.field(axis, int(f.offset), f"f{size}")
    colour = next((fields[n] for n in _COLOUR_FIELDS if n in fields), None)
    rgb = None
    if colour is not None and int(colour.datatype) in (_FLOAT32, _UINT32):
        # PCL packs 0x00RRGGBB (or AARRGGBB) into the bits of a float32: read them as uint32.
        rgb = view.field(colour.name, int(colour.offset), "u4").astype(np.uint32).reshape(-1)
    return xyz, rgb


@dataclass(frozen=True)
class _Strided:
    """Strided views of one field over a cloud's points (rows may be padded)."""

    data: npt.NDArray[np.uint8]
    width: int
    height: int
    step: int
    row_step: int
    order: str

    def field(self, name: str, offset: int, kind: str) -> npt.NDArray[Any]:
        """A (height, width) view of field *name* (numpy *kind*, e.g. ``f4``), no copy."""
        dtype = np.dtype(self.order + kind)
        if offset < 0 or offset + dtype.itemsize > self.step:
            raise ViewerCloudError(f"field {name} at offset {offset} does not fit "
                                   f"point_step {self.step}")
        end = (self.height - 1) * self.row_step + (self.width - 1) * self.step + offset
        need = end + dtype.itemsize
        if need > self.data.size:
            raise ViewerCloudError(f"data is {self.data.size} bytes, {self.height} x "
                                   f"{self.width} points of {self.step} need {need}")
        return np.ndarray((self.height, self.width), dtype, buffer=self.data, offset=offset,
                          strides=(self.row_step, self.step))


def _unpack_rgb(packed: npt.NDArray[np.uint32]) -> npt.NDArray[np.uint8]:
    """(n, 3) r, g, b from 0x??RRGGBB values."""
    as_bytes = packed.astype("<u4").view(np.uint8).reshape(-1, 4)
    return as_bytes[:, 2::-1]  # little-endian bytes are b, g, r, a


# --- quantization and de-duplication ---------------------------------------------------------


def _quantize(
    xyz: npt.NDArray[np.float64], resolution_m: float
) -> tuple[npt.NDArray[np.float32], np.float32, npt.NDArray[np.int16]]:
    """``(origin, resolution, index)``: float32 origin and resolution as sent, and voxel
    indices, shape (3, n), each in 0..MAX_INDEX."""
    n = xyz.shape[1]
    if n == 0:
        return np.zeros(3, np.float32), np.float32(resolution_m), np.empty((3, 0), np.int16)
    low = xyz.min(axis=1)
    origin = low.astype(np.float32)
    # The float32 origin may round above the minimum: step it down below.
    origin = np.where(origin.astype(np.float64) > low,
                      np.nextafter(origin, np.float32(-np.inf)), origin)
    base = origin.astype(np.float64)
    span = float((xyz.max(axis=1) - base).max())
    res = np.float32(resolution_m)
    if span / float(res) >= MAX_INDEX:
        # One voxel of headroom against rounding at the far edge.
        res = np.float32(span / (MAX_INDEX - 1))
    index = np.empty((3, n), np.int16)
    scratch = np.empty(n, np.float64)
    for axis in range(3):  # in place, one row at a time: no (3, n) temporaries
        np.subtract(xyz[axis], base[axis], out=scratch)
        np.divide(scratch, float(res), out=scratch)
        np.floor(scratch, out=scratch)
        np.clip(scratch, 0, MAX_INDEX, out=scratch)
        index[axis] = scratch
    return origin, res, index


def _voxel_order(index: npt.NDArray[np.int16]) -> npt.NDArray[np.intp]:
    """Positions of one point per voxel (the first in cloud order), sorted by (x, y, z).

    A lexsort of the int16 indices (numpy sorts 16-bit keys by radix: ~3.5 ms per 200k
    voxels, against ~20-30 ms for an argsort of packed 45-bit keys). Consecutive
    duplicates are dropped first: neighbouring pixels of an organized cloud often share a
    voxel, and that O(n) pass shrinks what the sort sees by a quarter at 1 cm.
    """
    if index.shape[1] == 0:
        return np.empty(0, np.intp)
    keep = np.flatnonzero(_run_starts(index))
    small = np.take(index, keep, axis=1)
    order = np.lexsort((small[2], small[1], small[0]))  # stable: x, then y, then z
    unique = _run_starts(np.take(small, order, axis=1))
    # A stable sort keeps cloud order within a voxel: each run starts with its first point.
    return keep[order[unique]]


def _run_starts(index: npt.NDArray[np.int16]) -> npt.NDArray[np.bool_]:
    """True where a column differs from the one before it (and for the first)."""
    starts = np.empty(index.shape[1], bool)
    starts[0] = True
    np.not_equal(index[0, 1:], index[0, :-1], out=starts[1:])
    for axis in (1, 2):
        starts[1:] |= index[axis, 1:] != index[axis, :-1]
    return starts


# --- the client's hook ---------------------------------------------------------------------


@dataclass
class ViewerClouds:
    """Sends ``<remote_topic>/viewer`` beside each cloud of an entry with ``viewer_cloud``.

    The viewer frame goes through the same send path as the cloud (called after the
    cloud's rate limit admitted it, so it has the same rate), with the cloud's priority,
    droppable, deflate-compressed. A cloud that cannot be encoded (no x/y/z) is still
    relayed in full; the first failure of each topic is logged at WARNING, later ones at
    DEBUG, all counted.

    Args:
        send: ``send(spec, msg, latched=...) -> bool`` encoding and queueing a message of
            ``spec.type`` (the bridge's ``send_message``).
        cls: The ViewerCloud message class (default: fleetctl's default registry's).
    """

    send: Callable[..., bool]
    cls: Any = None
    stats: ViewerCloudStats = field(default_factory=ViewerCloudStats)
    _specs: dict[PublishSpec, PublishSpec] = field(default_factory=dict)
    _warned: set[str] = field(default_factory=set)

    def on_cloud(self, spec: PublishSpec, msg: Any, *, latched: bool = False) -> bool:
        """Encode and send the viewer cloud of *msg* (a cloud of entry *spec*).

        Returns:
            False when the cloud could not be encoded or sent (logged, counted).
        """
        if spec.viewer_cloud is None:
            return False
        try:
            viewer = encode(msg, spec.viewer_cloud.resolution_m, cls=self.cls, stats=self.stats)
        except Exception as exc:  # never let a bad cloud stop the node or the full cloud
            self.stats.errors += 1
            level = logging.DEBUG if spec.topic in self._warned else logging.WARNING
            self._warned.add(spec.topic)
            log.log(level, "no viewer cloud for %s (the full cloud is still sent): %s",
                    spec.topic, exc)
            return False
        return self.send(self.viewer_spec(spec), viewer, latched=latched)

    def viewer_spec(self, spec: PublishSpec) -> PublishSpec:
        """The publish entry of *spec*'s viewer topic (cached)."""
        out = self._specs.get(spec)
        if out is None:
            out = self._specs[spec] = dataclasses.replace(
                spec, type=VIEWER_CLOUD_TYPE, remote_topic=spec.remote_topic + VIEWER_SUFFIX,
                no_drop=False, compression="deflate", viewer_cloud=None, video=None)
        return out
