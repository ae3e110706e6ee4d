"""Calibration of cameras, stereo rigs, hand-eye and fixed stations, with reports in millimetres."""
