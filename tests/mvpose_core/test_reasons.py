"""The one reason table: stable numbers, layer ranges, words for every code."""

from mvpose_core.reasons import DESCRIPTIONS, Reason, describe, reason_name


def test_station_and_link_codes_are_stable() -> None:
    # On the PLC interface, in every stored record: never renumber (gate codes: test_gate.py).
    assert {c.name: int(c) for c in Reason if c >= 100} == {
        "CAMERA_FAILED": 101, "DETECTION_FAILED": 102, "DEADLINE_EXCEEDED": 103,
        "UNKNOWN_RECIPE": 104, "UNKNOWN_VIEW": 105, "INTERNAL_ERROR": 106, "STORE_FAILED": 107,
        "TIMEOUT": 1001, "HANDLER_FAILED": 1002, "INVALID_OUTCOME": 1003, "BUSY": 1004,
        "UNKNOWN_COMMAND": 1005, "BAD_ARGUMENT": 1006,
    }


def test_every_code_has_words_and_a_name() -> None:
    assert set(DESCRIPTIONS) == set(Reason)
    assert describe(103) == "the result was not ready within the cycle deadline"
    assert describe(4242) == "unknown result code 4242"
    assert reason_name(1001) == "TIMEOUT"
    assert reason_name(77) == "CODE_77"


def test_the_operations_guide_has_the_table_of_the_code() -> None:
    """docs/operations.md's reason table is the one in mvpose_core/reasons.py (words and what
    to check), row for row: the line view shows the code's, the guide must not say otherwise."""
    from pathlib import Path

    from mvpose_core.reasons import CHECKS, reasons_table, what_to_check

    assert set(CHECKS) == set(Reason)
    assert what_to_check(1) == CHECKS[Reason.MARKS_MISSING]
    assert what_to_check(4242) == "the record's message and the log"
    guide = (Path(__file__).resolve().parents[2] / "docs" / "operations.md").read_text()
    table = reasons_table()
    assert table in guide, "docs/operations.md: paste mvpose_core.reasons.reasons_table() again"
    assert len(table.splitlines()) == 2 + len(Reason)
