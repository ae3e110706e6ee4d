"""The error family every driver raises, so callers never see a vendor exception.

Modelled on python-can: one base class, a class per failure phase, and a timeout that is also a
built-in :class:`TimeoutError`. Backends re-raise vendor exceptions ``from err`` so the original
traceback stays attached for the log while the caller handles one family.
"""

from __future__ import annotations


class DriverError(Exception):
    """Something went wrong in a driver (camera or PLC)."""


class DriverInitError(DriverError):
    """A device could not be found, opened or configured (unknown serial, bad setting)."""


class DriverOperationError(DriverError):
    """A device that was open failed while working (bad frame, lost link, wrong format)."""


class FrameFormatError(DriverOperationError):
    """A frame of the wrong size, bit depth or channel count: never cropped or converted to fit.
    The station reports it as ``Reason.DETECTION_FAILED`` (102), like the detector's own
    :class:`mvpose_core.detect.ImageFormatError` (docs/operations.md)."""


class DeviceLostError(DriverOperationError):
    """The device stopped answering; it must be closed and opened again."""


class DriverTimeout(DriverError, TimeoutError):  # noqa: N818 - the name the project chose
    """A device did not answer before the deadline."""
