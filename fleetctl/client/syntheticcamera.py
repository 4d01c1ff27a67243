"""A synthetic camera with motion, texture and sensor noise (pure: numpy, Pillow, skimage).

What the video benchmark (benchmarks/media/camera.py) and the simulated robot's raw camera
(:mod:`fleetctl.client.ros.simcamera`) show: a pan and zoom across a mosaic of four real
photographs from scikit-image's packaged data set (``astronaut``, ``rocket``, ``coffee`` and
``chelsea``, each scaled to 512 px high, 1279 x 1024 px in all), plus Gaussian sensor noise.

- Motion: the view's centre follows two sines (periods 12 s across, 9 s down) over the whole
  mosaic, up to ~5 px per frame at 30 Hz, while the zoom breathes between 1.0 and 1.4
  source pixels per output pixel (8 s period): every frame differs from the last one in
  position and scale, as from a robot driving and turning.
- Texture: the photographs at their native resolution (no upscaling at zoom 1.0):
  the fine detail of fur, wood grain and a launch tower's lattice, with sharp edges where
  the photographs meet.
- Without scikit-image (it is a development dependency, not in the robot image), the
  mosaic is procedural instead, of the same size: value noise at five octaves per
  channel (texture at every scale) under a few hundred seeded rectangles and discs with
  sharp edges (what a block-based encoder finds hardest). Same motion, same noise; the
  e2e load publisher's camera uses it.
- Noise: independent Gaussian noise per pixel and channel, sigma 2 (8-bit levels), as a
  well-lit CMOS sensor; a fresh draw per frame (``noise_bank=0``), or, where generating it
  would cost too much CPU at 30 Hz (the simulated robot), one of a bank of pre-drawn
  fields shifted by a random offset per frame.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetctl.client.video import Image

__all__ = ["CameraSequence", "mosaic", "procedural_mosaic"]

_ROW_PX = 512


@functools.lru_cache(maxsize=1)
def mosaic() -> Image:
    """The 1279 x 1024 px RGB mosaic the camera looks at (cached; read-only): the
    photographs when scikit-image is installed, else :func:`procedural_mosaic`."""
    try:
        import skimage.data
    except ImportError:
        return procedural_mosaic()
    from PIL import Image as PilImage

    def scaled(img: Image) -> Image:
        pil = PilImage.fromarray(img)
        width = round(pil.width * _ROW_PX / pil.height)
        return np.asarray(pil.resize((width, _ROW_PX), PilImage.Resampling.LANCZOS))

    data: Any = skimage.data  # untyped
    top = np.concatenate([data.astronaut(), scaled(data.rocket())], axis=1)
    bottom = np.concatenate([scaled(data.coffee()), scaled(data.chelsea())], axis=1)
    width = min(top.shape[1], bottom.shape[1])
    world = np.ascontiguousarray(np.concatenate([top[:, :width], bottom[:, :width]], axis=0))
    world.setflags(write=False)
    return world


_MOSAIC_W, _MOSAIC_H = 1279, 1024


@functools.lru_cache(maxsize=1)
def procedural_mosaic(seed: int = 7) -> Image:
    """A 1279 x 1024 px RGB world of value noise and sharp shapes (cached; read-only)."""
    from PIL import Image as PilImage
    from PIL import ImageDraw

    rng = np.random.default_rng(seed)
    field = np.zeros((_MOSAIC_H, _MOSAIC_W, 3), dtype=np.float32)
    for octave in range(5):
        cells = 4 * 2**octave  # 4 .. 64 cells across: features of ~320 px down to ~20 px
        grid = rng.random((cells * _MOSAIC_H // _MOSAIC_W + 2, cells + 2, 3))
        smooth = PilImage.fromarray((grid * 255).astype(np.uint8)).resize(
            (_MOSAIC_W, _MOSAIC_H), PilImage.Resampling.BICUBIC)
        field += np.asarray(smooth, dtype=np.float32) / 2**octave
    field *= 255 / field.max()
    world = PilImage.fromarray(field.astype(np.uint8))
    draw = ImageDraw.Draw(world)
    for _ in range(300):
        x, y = int(rng.integers(_MOSAIC_W)), int(rng.integers(_MOSAIC_H))
        w, h = (int(v) for v in rng.integers(6, 90, size=2))
        colour = tuple(int(c) for c in rng.integers(0, 256, size=3))
        if rng.random() < 0.5:
            draw.rectangle((x, y, x + w, y + h), fill=colour)
        else:
            draw.ellipse((x, y, x + w, y + w), fill=colour)
    out = np.ascontiguousarray(np.asarray(world))
    out.setflags(write=False)
    return out


class CameraSequence:
    """Frames of the synthetic camera (see the module docstring).

    Args:
        width: Frame width in pixels.
        height: Frame height in pixels.
        fps: Frame rate (Hz): frame *i* shows time ``i / fps``.
        noise_sigma: Standard deviation of the sensor noise (8-bit levels); 0: none.
        seed: Seed of the noise.
        noise_bank: 0 draws fresh noise per frame; N > 0 pre-draws N fields and shifts one
            per frame (cheaper: ~2 ms instead of ~10 ms per 640 x 480 frame).
    """

    def __init__(self, width: int = 640, height: int = 480, fps: float = 30.0,
                 noise_sigma: float = 2.0, seed: int = 0, noise_bank: int = 0) -> None:
        from PIL import Image as PilImage

        self.width, self.height, self.fps = width, height, fps
        self.noise_sigma = noise_sigma
        self._source = PilImage.fromarray(mosaic())
        self._rng = np.random.default_rng(seed)
        self._bank = [self._noise() for _ in range(noise_bank)] if noise_sigma > 0 else []

    def clean(self, index: int) -> Image:
        """Frame *index* without noise (``height x width x 3`` uint8 RGB)."""
        from PIL import Image as PilImage

        t = index / self.fps
        src_w, src_h = self._source.size
        zoom = 1.0 + 0.4 * (0.5 - 0.5 * math.cos(2 * math.pi * t / 8.0))
        view_w, view_h = self.width * zoom, self.height * zoom
        # Keep the view inside the mosaic at every zoom (10 px margin).
        cx = src_w / 2 + max(0.0, src_w / 2 - view_w / 2 - 10) * math.sin(2 * math.pi * t / 12)
        cy = src_h / 2 + max(0.0, src_h / 2 - view_h / 2 - 10) * math.sin(2 * math.pi * t / 9)
        affine = (zoom, 0.0, cx - view_w / 2, 0.0, zoom, cy - view_h / 2)
        view = self._source.transform((self.width, self.height), PilImage.Transform.AFFINE,
                                      affine, resample=PilImage.Resampling.BILINEAR)
        return np.asarray(view)

    def frame(self, index: int) -> Image:
        """Frame *index* with sensor noise (``height x width x 3`` uint8 RGB)."""
        clean = self.clean(index)
        if self.noise_sigma <= 0:
            return clean
        if self._bank:
            field = self._bank[index % len(self._bank)]
            shift = int(self._rng.integers(field.size))
            noise = np.roll(field.reshape(-1), shift).reshape(field.shape)
        else:
            noise = self._noise()
        noisy: Image = np.clip(clean.astype(np.int16) + noise, 0, 255).astype(np.uint8)
        return noisy

    def _noise(self) -> npt.NDArray[np.int16]:
        gauss = self._rng.standard_normal((self.height, self.width, 3), dtype=np.float32)
        noise: npt.NDArray[np.int16] = np.rint(gauss * self.noise_sigma).astype(np.int16)
        return noise
