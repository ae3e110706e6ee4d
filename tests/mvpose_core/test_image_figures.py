"""Focus and light figures of the live camera view, on synthetic images with known answers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mvpose_core.image_figures import clip_windows, downscale, focus_figure, image_figures


def marks_image(rng: np.random.Generator, blur_sigma: float = 0.0) -> np.ndarray:
    """Dark discs on a light background (the scene of a mark window), optionally defocused."""
    img = np.full((240, 320), 180, np.uint8)
    for x, y in ((60, 60), (160, 120), (260, 180)):
        cv2.circle(img, (x, y), 18, 40, -1, lineType=cv2.LINE_AA)
    img = cv2.add(img, rng.integers(0, 3, img.shape, dtype=np.uint8))
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    return img


def test_focus_falls_as_the_image_is_defocused() -> None:
    rng = np.random.default_rng(1)
    figures = [focus_figure(marks_image(rng, s))[0] for s in (0.0, 0.8, 1.5, 3.0, 6.0)]
    assert all(a > b for a, b in zip(figures, figures[1:], strict=False)), figures


def test_focus_over_the_mark_windows_ignores_the_rest_of_the_image() -> None:
    rng = np.random.default_rng(2)
    sharp = marks_image(rng)
    windows = [(30, 30, 90, 90), (130, 90, 190, 150)]
    clutter = sharp.copy()
    clutter[200:, :100] = rng.integers(0, 256, (40, 100), dtype=np.uint8)  # outside the windows
    a, area = focus_figure(sharp, windows)
    b, _ = focus_figure(clutter, windows)
    assert area == "mark windows" and a == pytest.approx(b)
    assert focus_figure(clutter)[0] > 2 * focus_figure(sharp)[0]  # the whole image sees it
    # pooled: the windows' variance, not one window's
    ones = [focus_figure(sharp, [w])[0] for w in windows]
    assert min(ones) <= a <= max(ones) * 1.5


def test_windows_outside_the_image_fall_back_to_the_whole_image() -> None:
    img = marks_image(np.random.default_rng(3))
    assert clip_windows([(-50, -50, 1, 1), (400, 0, 500, 100), (300, 200, 400, 300)],
                        320, 240) == [(300, 200, 320, 240)]
    focus, area = focus_figure(img, [(-50, -50, 1, 1)])
    assert area == "whole image" and focus == pytest.approx(focus_figure(img)[0])


def test_light_figures() -> None:
    img = np.full((400, 400), 100, np.uint8)
    img[:100] = 255  # a quarter saturated
    img[100:140] = 0  # a tenth without signal
    f = image_figures(img)
    assert f.saturated_pct == pytest.approx(25.0)
    assert f.dark_pct == pytest.approx(10.0)
    assert f.mean == pytest.approx(0.25 * 255 + 0.65 * 100)
    # estimated from a sample of the pixels: a scattered share is read within a fraction of 1 %
    rng = np.random.default_rng(5)
    noisy = rng.integers(1, 255, (2048, 2048), dtype=np.uint8)
    noisy[rng.random(noisy.shape) < 0.03] = 255
    assert image_figures(noisy).saturated_pct == pytest.approx(
        100 * np.mean(noisy == 255), abs=0.2)
    flat = image_figures(np.full((50, 50), 7, np.uint8))
    assert flat.focus == 0.0 and flat.saturated_pct == 0.0 and flat.mean == pytest.approx(7)


def test_downscale_by_a_whole_factor_keeps_the_aspect_and_never_enlarges() -> None:
    img = np.zeros((2048, 2448), np.uint8)
    img[4, 0] = img[0, 8] = 255
    small = downscale(img, 640)  # 2448 / 4 = 612 <= 640 < 2448 / 3
    assert small.shape == (512, 612) and small.dtype == np.uint8
    assert (small[1, 0], small[0, 2], small[0, 1]) == (255, 255, 0)
    assert downscale(small, 1000) is small
    assert downscale(np.zeros((2048, 2048), np.uint8), 640).shape == (512, 512)


def test_focus_is_the_variance_of_the_4_neighbour_laplacian() -> None:
    img = np.zeros((9, 9), np.uint8)
    img[4, 4] = 10  # one bright pixel: Laplacian 40 there, -10 at its 4 neighbours
    values = np.zeros((7, 7))  # the inner pixels, where the kernel fits
    values[3, 3], values[2, 3], values[4, 3], values[3, 2], values[3, 4] = 40, -10, -10, -10, -10
    assert focus_figure(img)[0] == pytest.approx(values.var())
    # a window takes the image around it: the same pixel's window sees the same values
    assert focus_figure(img, [(3, 3, 6, 6)])[0] == pytest.approx(values[2:5, 2:5].var())


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="mono8.*100x100x3 uint8"):
        image_figures(np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(ValueError, match="uint16"):
        focus_figure(np.zeros((10, 10), np.uint16))
    with pytest.raises(ValueError, match="width"):
        downscale(np.zeros((10, 10), np.uint8), 0)
