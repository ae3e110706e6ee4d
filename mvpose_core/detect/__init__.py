"""Circular-mark detection: window mode from a prior pose, search mode, centre correction, stereo.

Typical use per image: ``detect_marks(image, cam, recipe, T_rf_from_pf_prior)``; after the pose
is refined, ``correct_centres(detections, cam, recipe, T_rf_from_pf)`` recomputes the perspective
correction at the better pose; ``stereo_check`` drops marks whose cameras disagree.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mvpose_core.detect.geometry import (
    Ellipse,
    MarkPrediction,
    perspective_correction,
    predict_marks,
)
from mvpose_core.detect.search import identify_marks, search_marks
from mvpose_core.detect.stereo import EpipolarFailure, epipolar_distance_px, stereo_check
from mvpose_core.detect.types import DetectOptions, MarkDetection, check_image
from mvpose_core.detect.window import detect_marks
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

__all__ = [
    "DetectOptions",
    "Ellipse",
    "EpipolarFailure",
    "MarkDetection",
    "MarkPrediction",
    "check_image",
    "correct_centres",
    "detect_marks",
    "epipolar_distance_px",
    "identify_marks",
    "perspective_correction",
    "predict_marks",
    "search_marks",
    "stereo_check",
]


def correct_centres(
    detections: list[MarkDetection], cam: ViewCamera, recipe: RecipeConfig, T_rf_from_pf: Array
) -> list[MarkDetection]:
    """The detections with their centres corrected for perspective at the pose ``T_rf_from_pf``."""
    ids = [d.mark_id for d in detections if d.found and d.uv_ellipse is not None]
    corr = perspective_correction(cam, recipe, T_rf_from_pf, ids)
    out = []
    for d in detections:
        c = corr.get(d.mark_id)
        if not d.found or d.uv_ellipse is None or c is None:
            out.append(d)
            continue
        out.append(replace(d, uv=d.uv_ellipse + c, correction=np.asarray(c, dtype=float).copy()))
    return out
