"""The one table of result codes: what every record, every link and every report calls a result.

Stable numbers, one name each; they go on the PLC interface, into every record and every OPC UA
or MQTT message. Ranges say which layer decides a code:

- 0: OK.
- 1..99: the quality gate and the pose engine (``mvpose_core``).
- 100..999: the station (cameras, detection, deadline, recipe and view selection, store).
- 1000..: the link itself (a measurement or command the link could not get an answer to).

Once released, a number keeps its meaning; new codes are added, never renumbered.
"""

from __future__ import annotations

from enum import IntEnum


class Reason(IntEnum):
    """Why a result is what it is (0 = OK)."""

    OK = 0
    # -- gate and engine (1..99)
    MARKS_MISSING = 1
    NOT_CONVERGED = 2
    RESIDUAL_RMS_HIGH = 3
    RESIDUAL_MAX_HIGH = 4
    ROTATION_UNCERTAINTY_HIGH = 5
    TRANSLATION_UNCERTAINTY_HIGH = 6
    OFFSET_TRANSLATION_OUT_OF_RANGE = 7
    OFFSET_ROTATION_OUT_OF_RANGE = 8
    BAD_INPUT = 9
    TOO_FEW_MARKS = 10
    POSE_NOT_DETERMINED = 11
    MARK_BEHIND_CAMERA = 12
    # -- station (100..999)
    CAMERA_FAILED = 101  # a camera the recipe needs gave no frame, and marks are missing because
    DETECTION_FAILED = 102  # the detector refused an image (wrong size, bit depth, channels)
    DEADLINE_EXCEEDED = 103  # the result could not reach the link within station.deadline_ms
    UNKNOWN_RECIPE = 104  # a recipe number the station does not have
    UNKNOWN_VIEW = 105  # a view index the station does not have, or one the recipe never uses
    INTERNAL_ERROR = 106  # a bug: the exception is in the log and the record's reason text
    STORE_FAILED = 107  # neither the store nor the local journal took the record
    # -- link (1000..)
    TIMEOUT = 1001  # the measurement or command missed the link's deadline
    HANDLER_FAILED = 1002  # the measurement or command failed with an exception
    INVALID_OUTCOME = 1003  # the station answered non-finite or mis-sized values
    BUSY = 1004  # command refused: a measurement or another command is running
    UNKNOWN_COMMAND = 1005  # command code not known to the link
    BAD_ARGUMENT = 1006  # command argument out of range


def reason_name(code: int) -> str:
    """The table's name for ``code``; ``CODE_<n>`` for a number outside it."""
    try:
        return Reason(code).name
    except ValueError:
        return f"CODE_{code}"


# What an operator reads: each reason in words (the operator page, `mvpose demo`, reports).
DESCRIPTIONS: dict[Reason, str] = {
    Reason.OK: "measured within every tolerance",
    Reason.MARKS_MISSING: "marks the recipe needs were not found",
    Reason.NOT_CONVERGED: "the pose estimate did not converge",
    Reason.RESIDUAL_RMS_HIGH: "the marks do not fit the part model (RMS residual too high)",
    Reason.RESIDUAL_MAX_HIGH: "one mark does not fit the part model (largest residual too high)",
    Reason.ROTATION_UNCERTAINTY_HIGH: "the rotation is too uncertain for the grasp",
    Reason.TRANSLATION_UNCERTAINTY_HIGH: "the position is too uncertain for the grasp",
    Reason.OFFSET_TRANSLATION_OUT_OF_RANGE: "the part is shifted further than the recipe allows",
    Reason.OFFSET_ROTATION_OUT_OF_RANGE: "the part is turned further than the recipe allows",
    Reason.BAD_INPUT: "the measurement input was invalid",
    Reason.TOO_FEW_MARKS: "too few marks were seen to fix the pose",
    Reason.POSE_NOT_DETERMINED: "the marks seen do not fix the pose",
    Reason.MARK_BEHIND_CAMERA: "a mark lies behind a camera at the estimated pose",
    Reason.CAMERA_FAILED: "a camera gave no image",
    Reason.DETECTION_FAILED: "an image was refused (wrong size or format)",
    Reason.DEADLINE_EXCEEDED: "the result was not ready within the cycle deadline",
    Reason.UNKNOWN_RECIPE: "the selected recipe does not exist on this station",
    Reason.UNKNOWN_VIEW: "the view index is not one of the recipe's views",
    Reason.INTERNAL_ERROR: "software fault (see the log)",
    Reason.STORE_FAILED: "the result could not be stored",
    Reason.TIMEOUT: "no answer within the link's deadline",
    Reason.HANDLER_FAILED: "the station failed to answer (see the log)",
    Reason.INVALID_OUTCOME: "the station's answer could not be encoded for the link",
    Reason.BUSY: "refused: the station is busy",
    Reason.UNKNOWN_COMMAND: "unknown command",
    Reason.BAD_ARGUMENT: "command argument out of range",
}


def describe(code: int) -> str:
    """``code`` in an operator's words."""
    try:
        return DESCRIPTIONS[Reason(code)]
    except (ValueError, KeyError):
        return f"unknown result code {code}"


# What to check when a result has this reason: the line view's hint under each NOK and the
# table in docs/operations.md (tests/mvpose_core/test_reasons.py holds the docs to this table).
CHECKS: dict[Reason, str] = {
    Reason.OK: "nothing: the offset was sent",
    Reason.MARKS_MISSING: "dirt on a mark, the lighting, the part off its place",
    Reason.NOT_CONVERGED: "a mark mix-up or a bad calibration",
    Reason.RESIDUAL_RMS_HIGH: "a false mark, a moved camera, a stale calibration",
    Reason.RESIDUAL_MAX_HIGH: "a false mark, a moved camera, a stale calibration",
    Reason.ROTATION_UNCERTAINTY_HIGH: "marks seen too close together; the recipe's tolerance",
    Reason.TRANSLATION_UNCERTAINTY_HIGH: "marks seen too close together; the recipe's tolerance",
    Reason.OFFSET_TRANSLATION_OUT_OF_RANGE: "the part's place on the fixture (max_offset_mm)",
    Reason.OFFSET_ROTATION_OUT_OF_RANGE: "the part's place on the fixture (max_offset_deg)",
    Reason.BAD_INPUT: "the recipe and the station file (the record's message says what)",
    Reason.TOO_FEW_MARKS: "dirt, the lighting, a camera's view blocked",
    Reason.POSE_NOT_DETERMINED: "the recipe's marks and sightings (too few in one line)",
    Reason.MARK_BEHIND_CAMERA: "a mark mix-up or a camera's pose in the calibration",
    Reason.CAMERA_FAILED: "the camera's cable, power and status on the Live page",
    Reason.DETECTION_FAILED: "the camera's image size and pixel format against the station file",
    Reason.DEADLINE_EXCEEDED: "the cycle time chart on SPC; a slow camera or a busy machine",
    Reason.UNKNOWN_RECIPE: "the recipe number the PLC sends",
    Reason.UNKNOWN_VIEW: "the view index the PLC sends",
    Reason.INTERNAL_ERROR: "the log: it has the traceback; call the engineer",
    Reason.STORE_FAILED: "the disk (full?) and the database",
    Reason.TIMEOUT: "a stuck camera or detector: the camera's status, the log",
    Reason.HANDLER_FAILED: "the log: the station failed to answer",
    Reason.INVALID_OUTCOME: "the log: the answer did not fit the link's format",
    Reason.BUSY: "the PLC's handshake: a trigger sent while one was running",
    Reason.UNKNOWN_COMMAND: "the command code the PLC sends",
    Reason.BAD_ARGUMENT: "the command argument the PLC sends",
}


def what_to_check(code: int) -> str:
    """What to look at for a result with ``code`` (the line view's hint)."""
    try:
        return CHECKS[Reason(code)]
    except (ValueError, KeyError):
        return "the record's message and the log"


def reasons_table() -> str:
    """The Markdown table of every code, its name, its words and what to check
    (docs/operations.md holds a copy; a test keeps it equal to this)."""
    rows = ["| code | name | meaning | what to check |", "|---|---|---|---|"]
    rows += [f"| {r.value} | {r.name} | {DESCRIPTIONS[r]} | {CHECKS[r]} |" for r in Reason]
    return "\n".join(rows)
