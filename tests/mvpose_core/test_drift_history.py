"""The drift watch's history in numpy rings answers as the lists it replaced, to the last bit.

:class:`tests.mvpose_core.drift_lists.ListDriftWatch` is the watch as it was (lists trimmed to
``history`` once past twice as many); both watch a long synthetic stream of four cameras with
moves, returns, skipped cameras, partly fitted cameras and missing stamps, far past the point
where the rings wrap and the lists were trimmed, and are asked for every state after each
trigger.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mvpose_core.drift import DriftOptions, DriftWatch, drift_message
from mvpose_core.drift_history import History, Stamps, history_bytes
from mvpose_core.station import StationFileError, parse_station
from tests.mvpose_core.drift_lists import ListDriftWatch

STATION1 = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"

KEYS = [(1, "a"), (1, "b"), (1, "c"), (2, "a")]
H = 150


def _response(rng: np.random.Generator) -> dict:
    # a moved camera keeps most of its move and pushes a little into the others' residuals
    return {m: {s: (np.eye(2) * 0.8 + rng.normal(0, 0.1, (2, 2)) if s == m
                    else rng.normal(0, 0.15, (2, 2))) for s in KEYS} for m in KEYS}


def _stream(rng: np.random.Generator, triggers: int):
    """Per trigger: means, stamp and in-fit fractions, with a camera moving now and then."""
    moved, shift, until = None, np.zeros(2), -1
    for n in range(triggers):
        if n >= until and n % 97 == 0 and n > 100:
            moved = KEYS[int(rng.integers(len(KEYS)))]
            shift = rng.normal(0, 1.0, 2) * rng.choice([0.05, 0.1, 0.3])
            until = n + int(rng.integers(20, 120))
        elif n == until:
            moved = None
        means, in_fit = {}, {}
        for key in KEYS:
            if key == (1, "c") and rng.random() < 0.3:
                continue  # a camera that saw no mark this time skips the trigger
            x = rng.normal([0.01, -0.02], 0.03)
            if key == moved:
                x = x + shift
            means[key] = x
            in_fit[key] = 1.0 if rng.random() < 0.8 else float(rng.integers(3, 10)) / 10
        stamp = None if n % 53 == 7 else 1.7e9 + 0.731 * n
        yield means, stamp, in_fit


def test_rings_answer_as_the_lists_past_the_trimming_point() -> None:
    rng = np.random.default_rng(11)
    o = DriftOptions(warmup=40, history=H, h_warn=6.0, h_alarm=9.0)
    response = _response(rng)
    new, old = DriftWatch(o, response), ListDriftWatch(o, response)
    new.set_baseline((2, "a"), (0.01, -0.02), (0.03, 0.03))  # one camera given, not learnt
    old.set_baseline((2, "a"), (0.01, -0.02), (0.03, 0.03))
    compared = older = 0
    for means, stamp, in_fit in _stream(rng, 12 * H):
        new.update(means, stamp, in_fit)
        old.update(means, stamp, in_fit)
        assert new.statistics() == old.statistics()
        n = new.triggers
        for a, b in zip(new.states(), old.states(), strict=True):
            if a.since_trigger is None or a.since_trigger >= n - H:
                # every camera still holds all its updates since the change point
                assert a == b
                assert drift_message(a, "08:12") == drift_message(b, "08:12")
                compared += a.since_trigger is not None and a.shift_px is not None
            else:  # older than the history: measured over the kept updates only
                older += 1
                assert (a.status, a.statistic, a.moved is None, a.since_trigger) == (
                    b.status, b.statistic, b.moved is None, b.since_trigger)
                assert a.since is None
    assert new.triggers > 4 * H  # the lists were trimmed, the rings wrapped, several times
    assert compared > 200, compared  # states in warning or alarm, with a move, dated
    assert older > 0  # a run started before the history also occurred (a weak shift)


def test_history_ring_matches_a_plain_search_at_every_wrap() -> None:
    rng = np.random.default_rng(3)
    h = History(7, -1)
    idx: list[int] = []
    cum = [(0.0, 0.0, 0.0)]
    n = 0
    for _ in range(40):
        n += int(rng.integers(1, 4))
        d = rng.normal(size=3)
        h.append(n, float(d[0]), float(d[1]), float(d[2]))
        idx.append(n)
        a, b, c = cum[-1]
        cum.append((a + float(d[0]), b + float(d[1]), c + float(d[2])))
        kept = idx[-7:]
        for n0 in range(kept[0], n + 2):
            got = h.since(n0)
            j = next((i for i, k in enumerate(idx) if k >= n0), None)
            if j is None:
                assert got is None
                continue
            want = (np.asarray(cum[-1]) - np.asarray(cum[j])) / (len(idx) - j)
            assert got is not None and got.tolist() == want.tolist()
    assert h.nbytes == 7 * 32


def test_stamps_ring_forgets_the_oldest_and_keeps_none() -> None:
    s = Stamps(3)
    for t in (1.0, None, 3.0, 4.0):
        s.append(t)
    assert [s.get(i) for i in range(-1, 5)] == [None, None, None, 3.0, 4.0, None]
    s.append(5.0)
    assert (s.get(1), s.get(2)) == (None, 3.0)


def test_history_is_bounded_and_its_size_stated() -> None:
    o = DriftOptions(warmup=2, history=500)
    w = DriftWatch(o)
    rng = np.random.default_rng(0)
    for _ in range(3 * 500):
        w.update({k: rng.normal(0, 0.1, 2) for k in KEYS}, 1.0)
    assert w.history_nbytes == history_bytes(len(KEYS), 500) == 500 * (4 * 32 + 8)
    # at the default, 20,000
    assert history_bytes(4, DriftOptions().history) == pytest.approx(2.6 * 2**20, rel=0.01)


def test_station_file_sets_the_history_and_a_bad_one_is_named() -> None:
    data = yaml.safe_load(STATION1.read_text())
    assert parse_station(data, "st1.yaml").drift.history == DriftOptions().history
    data["drift"] = {"history": 2000}
    assert parse_station(data, "st1.yaml").drift.history == 2000
    data["drift"] = {"history": 10}
    with pytest.raises(StationFileError, match=r"st1\.yaml: drift\.history: .*100.*10\)"):
        parse_station(data, "st1.yaml")
    data["drift"] = {"histroy": 2000}
    with pytest.raises(StationFileError, match=r"drift\.histroy"):
        parse_station(data, "st1.yaml")
