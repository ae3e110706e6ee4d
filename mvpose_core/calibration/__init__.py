"""Calibration of cameras, stereo rigs, hand-eye and fixed stations, with reports in millimetres."""

from mvpose_core.calibration.files import (
    CalibrationFile,
    CalibrationFileError,
    CalibrationRef,
    apply_calibration,
    calibrated_station,
    load_calibration,
    save_calibration,
)

__all__ = [
    "CalibrationFile",
    "CalibrationFileError",
    "CalibrationRef",
    "apply_calibration",
    "calibrated_station",
    "load_calibration",
    "save_calibration",
]
