"""Count drawn pixels in a screenshot: the test's proof that something was really drawn."""

from __future__ import annotations

import io
import time
from typing import Any

import numpy as np
from PIL import Image


def drawn_pixels(png: bytes, background: tuple[int, int, int], tolerance: int = 40) -> int:
    """Pixels whose colour differs from *background* by more than *tolerance* (sum of |d|)."""
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    diff = np.abs(rgb - np.array(background, dtype=np.int16)).sum(axis=2)
    return int((diff > tolerance).sum())


def drawn_fraction(png: bytes, background: tuple[int, int, int], tolerance: int = 40) -> float:
    """Like :func:`drawn_pixels`, as a fraction of the image area (independent of scale)."""
    size = Image.open(io.BytesIO(png)).size
    return drawn_pixels(png, background, tolerance) / (size[0] * size[1])


def colored_pixels(png: bytes, color: tuple[int, int, int], tolerance: int = 60) -> int:
    """Pixels within *tolerance* (sum of |d|) of *color*: what one kind of object drew."""
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    diff = np.abs(rgb - np.array(color, dtype=np.int16)).sum(axis=2)
    return int((diff <= tolerance).sum())


async def drawn_fraction_within(locator: Any, background: tuple[int, int, int],
                                at_least: float, timeout_s: float = 10.0) -> float:
    """The drawn fraction of *locator*'s screenshot, retaken until it exceeds *at_least* or
    *timeout_s* passes; returns the best seen (the caller asserts on it).

    Why retake: an element screenshot is the element's box at capture time, and other panels
    still filling in (the TF tree growing, a status line appearing) can move the canvas
    between Playwright measuring the box and capturing it; the shot then holds part of the
    panel around the canvas. Waiting for the picture, with a deadline, is not the same as
    accepting less of it.
    """
    deadline = time.monotonic() + timeout_s
    best = 0.0
    while True:
        best = max(best, drawn_fraction(await locator.screenshot(), background))
        if best > at_least or time.monotonic() >= deadline:
            return best
