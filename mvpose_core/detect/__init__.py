"""Circular-mark detection: window mode from a prior pose, search mode, centre correction, stereo.

Typical use per image: ``detect_marks(image, cam, recipe, T_rf_from_pf_prior)``; after the pose
is refined, ``correct_centres(detections, cam, recipe, T_rf_from_pf)`` recomputes the perspective
correction at the better pose; ``stereo_check`` drops marks whose cameras disagree.
"""

from __future__ import annotations

from mvpose_core.detect.correction import (
    corrected,
    corrections_at,
    perspective_correction,
    perspective_corrections,
)
from mvpose_core.detect.ellipse import Ellipse
from mvpose_core.detect.geometry import MarkPrediction, predict_marks
from mvpose_core.detect.search import identify_marks, search_marks
from mvpose_core.detect.stereo import EpipolarFailure, epipolar_distance_px, stereo_check
from mvpose_core.detect.types import (
    DetectOptions,
    ImageFormatError,
    MarkDetection,
    check_image,
    image_format,
)
from mvpose_core.detect.window import detect_marks, detect_marks_many
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

__all__ = [
    "DetectOptions",
    "Ellipse",
    "EpipolarFailure",
    "ImageFormatError",
    "MarkDetection",
    "MarkPrediction",
    "check_image",
    "correct_centres",
    "corrected",
    "corrections_at",
    "detect_marks",
    "detect_marks_many",
    "epipolar_distance_px",
    "identify_marks",
    "image_format",
    "perspective_correction",
    "perspective_corrections",
    "predict_marks",
    "recorrect",
    "search_marks",
    "stereo_check",
]


def correct_centres(
    detections: list[MarkDetection], cam: ViewCamera, recipe: RecipeConfig, T_rf_from_pf: Array
) -> list[MarkDetection]:
    """The detections with their centres corrected for perspective at the pose ``T_rf_from_pf``."""
    return recorrect([(cam, detections)], recipe, T_rf_from_pf)[0][0]


def recorrect(
    groups: list[tuple[ViewCamera, list[MarkDetection]]], recipe: RecipeConfig,
    T_rf_from_pf: Array,
) -> tuple[list[list[MarkDetection]], float]:
    """Each camera's detections corrected for perspective at ``T_rf_from_pf``, and the largest
    change (px) of any correction against the one the detections carried (none: 0 px).
    :func:`corrections_at` gives the change without rebuilding the detections."""
    corrs, worst = corrections_at(groups, recipe, T_rf_from_pf)
    return corrected(groups, corrs), worst
