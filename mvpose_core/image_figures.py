"""Figures of one camera image for setting focus and light by hand (the live camera view).

- focus: the variance of the image's Laplacian (the 4-neighbour kernel: 4·centre minus its
  left, right, upper and lower neighbours) in grey levels², over the mark windows when there
  are any (the detector's search windows, where sharp edges matter), else over the whole image.
  A sharper image has stronger second derivatives at its edges: turning the focus ring, the
  figure peaks where the marks are sharpest. It has no absolute scale (it grows with contrast,
  light and noise), so it compares frames of one camera of one scene.
- light: the mean grey level (0-255) of the image and the share of its pixels at 255
  (saturated: an edge that clips there cannot be located) and at 0 (no signal), in percent,
  estimated from every :data:`LIGHT_STEP`-th pixel of every LIGHT_STEP-th row (1/16 of a
  2048 x 2048 frame's pixels: the estimate is within a fraction of a per cent, at 1/16 of the
  time).

Pure functions of arrays, as everything in mvpose_core, in numpy alone: numpy's loops release
the GIL, and unlike OpenCV's they run on the calling thread. The station computes these on a
niced thread beside its real-time trigger path; OpenCV would hand the work to its own thread
pool, whose threads run at the trigger path's real-time priority (they are started by it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: a window ``(x0, y0, x1, y1)`` in pixels, half-open, as the detector's search windows
Window = tuple[int, int, int, int]
#: the light figures look at every LIGHT_STEP-th pixel of every LIGHT_STEP-th row
LIGHT_STEP = 4


@dataclass(frozen=True)
class ImageFigures:
    """Focus and light figures of one image (see the module's docstring)."""

    focus: float  # variance of the Laplacian, grey levels²
    focus_area: str  # "mark windows" or "whole image"
    mean: float  # mean grey level, 0-255
    saturated_pct: float  # pixels at 255, percent
    dark_pct: float  # pixels at 0, percent


def _check(image: NDArray[np.uint8]) -> None:
    if image.dtype != np.uint8 or image.ndim != 2 or min(image.shape) < 3:
        shape = "x".join(map(str, image.shape))
        raise ValueError(f"image figures need a mono8 image of at least 3x3 pixels, got "
                         f"{shape} {image.dtype}")


def clip_windows(windows: Sequence[Window], width: int, height: int) -> list[Window]:
    """The windows cut to the image; those with fewer than 3x3 pixels inside are left out."""
    out = []
    for x0, y0, x1, y1 in windows:
        a, b = max(0, int(x0)), max(0, int(y0))
        c, d = min(width, int(x1)), min(height, int(y1))
        if c - a >= 3 and d - b >= 3:
            out.append((a, b, c, d))
    return out


def _laplacian(block: NDArray[np.uint8]) -> NDArray[np.int16]:
    """The 4-neighbour Laplacian of the block's inner pixels, ``["H-2", "W-2"]``."""
    b = block.astype(np.int16)
    out: NDArray[np.int16] = 4 * b[1:-1, 1:-1] - b[:-2, 1:-1] - b[2:, 1:-1] - b[1:-1, :-2] \
        - b[1:-1, 2:]
    return out


def focus_figure(image: NDArray[np.uint8], windows: Sequence[Window] = ()) -> tuple[float, str]:
    """The variance of the Laplacian over ``windows`` (those inside the image), or over the
    whole image when none is; with the name of the area it was taken over."""
    _check(image)
    h, w = image.shape
    inside = clip_windows(windows, w, h)
    area = "mark windows" if inside else "whole image"
    # Each window's Laplacian is taken with the image around it (no artificial border), then
    # all windows' values are pooled: one figure for the marks of the camera.
    n, s, s2 = 0, 0.0, 0.0
    for x0, y0, x1, y1 in inside or [(0, 0, w, h)]:
        a, b = max(0, x0 - 1), max(0, y0 - 1)
        c, d = min(w, x1 + 1), min(h, y1 + 1)
        lap = _laplacian(image[b:d, a:c])  # covers (a+1 .. c-1) x (b+1 .. d-1)
        core = lap[max(0, y0 - b - 1) : y1 - b - 1, max(0, x0 - a - 1) : x1 - a - 1]
        if core.size == 0:
            continue
        n += core.size
        s += float(core.sum(dtype=np.int64))
        s2 += float(np.square(core, dtype=np.int64).sum())
    if n == 0:
        return 0.0, area
    mean = s / n
    return max(0.0, s2 / n - mean * mean), area


def image_figures(image: NDArray[np.uint8], windows: Sequence[Window] = ()) -> ImageFigures:
    """Focus (over ``windows`` when any lies in the image) and light of a mono8 image."""
    focus, area = focus_figure(image, windows)
    sample = image[::LIGHT_STEP, ::LIGHT_STEP]
    total = float(sample.size)
    return ImageFigures(
        focus=focus,
        focus_area=area,
        mean=float(sample.mean(dtype=np.float64)),
        saturated_pct=100.0 * np.count_nonzero(sample == 255) / total,
        dark_pct=100.0 * np.count_nonzero(sample == 0) / total,
    )


def downscale(image: NDArray[np.uint8], width: int) -> NDArray[np.uint8]:
    """The image reduced by the smallest whole factor k that makes it at most ``width`` pixels
    wide: every k-th pixel of every k-th row (a picture to aim and focus by, not to measure:
    one copy of 1/k² of the pixels, where a block mean took 10 times as long); never
    enlarged."""
    _check(image)
    if width < 1:
        raise ValueError(f"downscale width must be at least 1 px, got {width}")
    k = -(-image.shape[1] // width)  # ceil
    if k <= 1:
        return image
    return np.ascontiguousarray(image[::k, ::k])
