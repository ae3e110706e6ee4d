"""Records and options of the mark detector, and the check every image passes at the public edge."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mvpose_core.camera import CameraModel
from mvpose_core.reasons import Reason
from mvpose_core.transforms import Array


@dataclass(frozen=True)
class DetectOptions:
    """Detector settings; the defaults suit 8-bit images of marks with radius 4–60 px."""

    min_contrast: float = 20.0  # grey levels between a mark and its surroundings
    max_fit_residual_px: float = 0.25  # RMS distance of edge points to the fitted ellipse
    size_tolerance: float = 0.15  # relative size slack beyond what the recipe's tolerances allow
    shape_slack_deg: float = 8.0  # tilt slack when checking the axis ratio
    min_edge_fraction: float = 0.8  # rays that must find the mark's edge
    window_extra_px: float = 6.0  # added to every window beyond the geometric margin
    search_scale: int = 4  # search mode: candidates on a 1/search_scale image
    correct_perspective: bool = True  # move the ellipse centre to the image of the circle centre
    max_candidates: int = 64  # per window or search: a busy image is not searched forever
    max_alternates: int = 3  # next candidates kept per mark for the estimator (MarkDetection)
    # Window mode searches first in windows for a part within ±first_reach_mm and
    # ±first_reach_deg of the prior pose (where parts usually arrive), when the recipe's
    # tolerances are wider; an image where some mark was not found there is searched again
    # over the whole tolerance. None: the whole tolerance at once.
    first_reach_mm: float | None = 25.0
    first_reach_deg: float = 2.5

    def first_reach(self, max_offset_mm: float, max_offset_deg: float) -> float | None:
        """The first search's share of a recipe's tolerances, or None for a single search (no
        first reach, or tolerances no wider than it)."""
        if self.first_reach_mm is None:
            return None
        share = max(self.first_reach_mm / max(max_offset_mm, 1e-9),
                    self.first_reach_deg / max(max_offset_deg, 1e-9))
        return share if share < 1.0 else None

    def __post_init__(self) -> None:
        if self.search_scale not in (1, 2, 4, 8):
            raise ValueError(
                f"DetectOptions.search_scale must be 1, 2, 4 or 8, got {self.search_scale}"
            )
        if self.first_reach_mm is not None and not (
            self.first_reach_mm > 0 and self.first_reach_deg > 0
        ):
            raise ValueError(
                f"DetectOptions.first_reach_mm and first_reach_deg must be > 0 (or "
                f"first_reach_mm None), got {self.first_reach_mm}, {self.first_reach_deg}"
            )
        if not 0 < self.min_edge_fraction <= 1:
            raise ValueError(
                f"DetectOptions.min_edge_fraction must be in (0, 1], got {self.min_edge_fraction}"
            )
        for name in ("min_contrast", "max_fit_residual_px", "size_tolerance", "window_extra_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"DetectOptions.{name} must be finite and >= 0, got {v}")


@dataclass(frozen=True)
class MarkDetection:
    """One mark in one image: where it is, how good it looks, or why it was not accepted.

    ``uv`` is the corrected centre (the image of the circle's centre, distorted pixels) when
    ``found``; ``uv_ellipse`` the centre of the fitted ellipse and ``correction`` what was added.
    """

    mark_id: str
    found: bool
    uv: Array | None
    reason: str | None = (
        None  # why not found / rejected ("outside window", "low contrast", "shape", ...)
    )
    contrast: float = 0.0  # grey levels, positive for the recipe's polarity
    fit_residual_px: float = float("nan")  # RMS of edge points to the ellipse
    axis_ratio: float = float("nan")  # minor / major axis
    radius_px: float = float("nan")  # sqrt(major · minor) semi-axes
    uv_ellipse: Array | None = None
    correction: Array | None = None
    edge_points: int = 0
    #: ellipse centres of the mark's next candidates (other accepted blobs in its window that
    #: no mark took), nearest to the prediction first
    alternates: tuple[tuple[float, float], ...] = ()

    def candidates(self) -> list[Array]:
        """The mark's centre and its next candidates' centres, corrected alike (``[2]`` each)."""
        if not self.found or self.uv is None:
            return []
        corr = self.correction if self.correction is not None else np.zeros(2)
        return [self.uv] + [np.array(a, dtype=float) + corr for a in self.alternates]

    @classmethod
    def missing(cls, mark_id: str, reason: str, **quality: float) -> MarkDetection:
        return cls(mark_id=mark_id, found=False, uv=None, reason=reason, **quality)  # type: ignore[arg-type]

    @classmethod
    def unnamed(
        cls,
        centre: Array,
        radius_px: float,
        axis_ratio: float,
        contrast: float,
        fit_residual_px: float,
        edge_points: int,
    ) -> MarkDetection:
        """A found blob not yet given a mark's identity (its centre still uncorrected)."""
        return cls(
            mark_id="",
            found=True,
            uv=centre.copy(),
            contrast=contrast,
            fit_residual_px=fit_residual_px,
            axis_ratio=axis_ratio,
            radius_px=radius_px,
            uv_ellipse=centre.copy(),
            correction=np.zeros(2),
            edge_points=edge_points,
        )

    def rejected(self, reason: str) -> MarkDetection:
        """This detection, not accepted any more (e.g. by the stereo check), with the reason."""
        return replace(self, found=False, reason=reason)


class ImageFormatError(ValueError):
    """An image of the wrong size, bit depth or channel count; reported as
    ``Reason.DETECTION_FAILED`` (docs/operations.md). Never cropped or converted to fit."""

    reason = Reason.DETECTION_FAILED


def image_format(image: np.ndarray) -> str:
    """``"WxH mono8"``-style name of an array's format (``mono16``, ``3-channel 8-bit`` …)."""
    if image.ndim < 2:
        return f"shape {'x'.join(map(str, image.shape)) or '()'} {image.dtype}"
    size = f"{image.shape[1]}x{image.shape[0]}"
    integer = image.dtype.kind in "ui"
    if image.ndim == 2:
        return f"{size} mono{image.dtype.itemsize * 8}" if integer else f"{size} {image.dtype}"
    channels = "x".join(map(str, image.shape[2:]))
    bits = f"{image.dtype.itemsize * 8}-bit" if integer else str(image.dtype)
    return f"{size} {channels}-channel {bits}"


def check_image(image: object, model: CameraModel, what: str) -> np.ndarray:
    """The image as a 2-D uint8 array of the camera's size, else :class:`ImageFormatError`
    naming ``what`` (the camera), the expected and the actual format, e.g. ``"camera 'v1/left1':
    expected 2048x2048 mono8, got 2560x2560 mono8"``. A larger frame is refused, never cropped."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.shape == (
        model.height, model.width
    ):
        return image  # the usual case, checked once per image per trigger: no more work
    want = f"{model.width}x{model.height} mono8"
    if not isinstance(image, np.ndarray):
        raise ImageFormatError(f"{what}: expected {want}, got {type(image).__name__}")
    if image.size == 0:
        raise ImageFormatError(
            f"{what}: expected {want}, got an empty image (shape "
            f"{'x'.join(map(str, image.shape)) or '()'})"
        )
    raise ImageFormatError(f"{what}: expected {want}, got {image_format(image)}")
