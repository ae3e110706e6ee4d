"""Records and options of the mark detector, and the check every image passes at the public edge."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mvpose_core.camera import CameraModel
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


def check_image(image: object, model: CameraModel, what: str) -> np.ndarray:
    """The image as a 2-D uint8 array of the camera's size, or ``ValueError`` naming the problem."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{what}: expected a numpy image, got {type(image).__name__}")
    if image.dtype == np.uint8 and image.shape == (model.height, model.width):
        return image  # the usual case, checked once per image per trigger: no more work
    shape = "x".join(str(s) for s in image.shape)
    if image.size == 0:
        raise ValueError(f"{what}: the image is empty (shape {shape or '()'})")
    if image.dtype != np.uint8:
        raise ValueError(
            f"{what}: expected a mono8 (uint8) image, got dtype {image.dtype} shape {shape}"
        )
    if image.ndim != 2:
        raise ValueError(f"{what}: expected a 2-D mono image, got shape {shape}")
    raise ValueError(
        f"{what}: expected {model.width}x{model.height} mono8, "
        f"got {image.shape[1]}x{image.shape[0]}"
    )
