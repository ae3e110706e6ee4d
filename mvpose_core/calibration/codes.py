"""The codes a robot-driven hand-eye session answers each step with (every link shows them).

Apart from :mod:`mvpose_core.calibration.session` so a link can name them without importing
the solvers. They lie above the result reasons (``mvpose_core.reasons``: 0-107, 1001-1006), so
a PLC's command result register never holds a number with two meanings.
"""

from __future__ import annotations

from enum import IntEnum


class HandEyeCode(IntEnum):
    """The answer to each step of a hand-eye session (a link's command result)."""

    OK = 0
    NO_SESSION = 201  # add or calculate without a begun session
    TOO_FEW_POSES = 202  # fewer poses than the solve plus the hold-out need
    TOO_LITTLE_ROTATION = 203  # pure translations, or rotations about one axis only
    UNIT_SUSPICIOUS = 204  # mm vs m, or degrees vs radians
    BOARD_NOT_FOUND = 205  # no camera of the rig found the board in this pose (not kept)
    OUTLIERS = 206  # too few poses left after leaving out the outliers
    BOARD_SCALE = 207  # the robot's motion says the board is not its declared size
    POSES_DO_NOT_FIT = 208  # wrong convention, inverted poses, poses paired wrongly
    BAD_POSE = 209  # the pose is not a pose (missing, non-finite, zero quaternion)
    CAPTURE_FAILED = 210  # a camera of the rig gave no image
    SESSION_FULL = 211  # MAX_POSES poses added already
    NOT_AVAILABLE = 212  # the station cannot run one (no robot-mounted rig, no board defined)
    FAILED = 213  # the solve failed otherwise (the message says how)
