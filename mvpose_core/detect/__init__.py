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
    perspective_corrections,
    predict_marks,
)
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
    change (px) of any correction against the one the detections carried (none: 0 px)."""
    usable = [
        [d for d in dets if d.found and d.uv_ellipse is not None] for _, dets in groups
    ]
    corrs = perspective_corrections(
        [(cam, [d.mark_id for d in ds]) for (cam, _), ds in zip(groups, usable, strict=True)],
        recipe, T_rf_from_pf,
    )
    worst = 0.0
    out = []
    for (_, dets), corr in zip(groups, corrs, strict=True):
        moved = []
        for d in dets:
            c = corr.get(d.mark_id)
            if not d.found or d.uv_ellipse is None or c is None:
                moved.append(d)
                continue
            before = d.correction if d.correction is not None else np.zeros(2)
            worst = max(worst, float(np.hypot(c[0] - before[0], c[1] - before[1])))
            moved.append(replace(d, uv=d.uv_ellipse + c, correction=np.array(c, dtype=float)))
        out.append(moved)
    return out, worst
