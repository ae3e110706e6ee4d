"""Figures of one camera image for setting focus and light by hand (the live camera view).

- focus: the variance of the image's Laplacian (3x3 kernel) in grey levels², over the mark
  windows when there are any (the detector's search windows, where sharp edges matter), else
  over the whole image. A sharper image has stronger second derivatives at its edges: turning
  the focus ring, the figure peaks where the marks are sharpest. It has no absolute scale (it
  grows with contrast, light and noise), so it compares frames of one camera of one scene.
- light: the mean grey level (0-255) of the whole image and the share of pixels at 255
  (saturated: an edge that clips there cannot be located) and at 0 (no signal), in percent.

Pure functions of arrays, as everything in mvpose_core. The pixel loops are OpenCV's, which
release the GIL: the station computes these beside its trigger thread.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

#: a window ``(x0, y0, x1, y1)`` in pixels, half-open, as the detector's search windows
Window = tuple[int, int, int, int]


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


def focus_figure(image: NDArray[np.uint8], windows: Sequence[Window] = ()) -> tuple[float, str]:
    """The variance of the Laplacian over ``windows`` (those inside the image), or over the
    whole image when none is; with the name of the area it was taken over."""
    _check(image)
    h, w = image.shape
    inside = clip_windows(windows, w, h)
    if not inside:
        std = cv2.meanStdDev(cv2.Laplacian(image, cv2.CV_32F, ksize=3))[1]
        return float(std[0, 0]) ** 2, "whole image"
    # Each window's Laplacian is taken with the image around it (no artificial border), then
    # all windows' values are pooled: one figure for the marks of the camera.
    n, s, s2 = 0, 0.0, 0.0
    for x0, y0, x1, y1 in inside:
        a, b = max(0, x0 - 1), max(0, y0 - 1)
        lap = cv2.Laplacian(image[b : min(h, y1 + 1), a : min(w, x1 + 1)], cv2.CV_32F, ksize=3)
        core = np.ascontiguousarray(lap[y0 - b : y0 - b + (y1 - y0), x0 - a : x0 - a + (x1 - x0)])
        m, sd = (float(v[0, 0]) for v in cv2.meanStdDev(core))
        k = core.size
        n += k
        s += k * m
        s2 += k * (sd * sd + m * m)
    mean = s / n
    return max(0.0, s2 / n - mean * mean), "mark windows"


def image_figures(image: NDArray[np.uint8], windows: Sequence[Window] = ()) -> ImageFigures:
    """Focus (over ``windows`` when any lies in the image) and light of a mono8 image."""
    focus, area = focus_figure(image, windows)
    hist = cv2.calcHist([image], [0], None, [256], [0, 256])[:, 0].astype(float)
    total = float(image.size)
    return ImageFigures(
        focus=focus,
        focus_area=area,
        mean=float(np.dot(hist, np.arange(256)) / total),
        saturated_pct=100.0 * float(hist[255]) / total,
        dark_pct=100.0 * float(hist[0]) / total,
    )


def downscale(image: NDArray[np.uint8], width: int) -> NDArray[np.uint8]:
    """The image at ``width`` pixels wide (area averaging, aspect kept); never enlarged."""
    _check(image)
    if width < 1:
        raise ValueError(f"downscale width must be at least 1 px, got {width}")
    h, w = image.shape
    if w <= width:
        return image
    height = max(1, round(h * width / w))
    out = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return out.astype(np.uint8, copy=False)
