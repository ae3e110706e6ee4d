"""The perspective correction at the estimated pose (mvpose_core.detect.correction): its few rim
points give the correction of the window prediction's dense rim, on every station we have."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import real_stations

from mvpose_core.detect import corrected, corrections_at, perspective_corrections, recorrect
from mvpose_core.detect.correction import CORRECTION_RIM_SAMPLES
from mvpose_core.detect.geometry import predict_marks
from mvpose_core.detect.types import MarkDetection
from mvpose_core.scene import sighted_marks, view_cameras
from mvpose_core.station import StationConfig, load_station
from mvpose_core.synth import displaced

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"


def _stations() -> list[tuple[str, StationConfig]]:
    files = sorted(STATIONS.glob("*.yaml")) + sorted((STATIONS / "scaling").glob("*.yaml"))
    out = [(f.stem, load_station(f)) for f in files]
    out += [(f.__name__, f()) for f in (real_stations.bonnet, real_stations.floor,
                                        real_stations.compact)]
    return out


@pytest.mark.parametrize(("name", "station"), _stations(), ids=lambda v: v if isinstance(v, str)
                         else "")
def test_the_sparse_rim_gives_the_dense_rims_correction(name: str, station: StationConfig) -> None:
    """16 rim points against the 72 of the window prediction (and 360), at poses over the
    whole tolerance: the same correction to < 1e-4 px (in fact to rounding, ~1e-12 px)."""
    rng = np.random.default_rng(5)
    cams = view_cameras(station)
    checked = 0
    for recipe in station.recipes:
        asked = [(c, sighted_marks(recipe, c.view, c.camera_id)) for c in cams]
        for _ in range(4):
            T = displaced(recipe, float(rng.uniform(-1.0, 1.0)), rng.normal(size=3),
                          rng.normal(size=3))
            sparse = perspective_corrections(asked, recipe, T)
            dense = perspective_corrections(asked, recipe, T, rim_samples=360)
            for (cam, ids), s, d in zip(asked, sparse, dense, strict=True):
                assert s.keys() == d.keys()
                preds = {p.mark.mark_id: p for p in predict_marks(cam, recipe, T)}
                for mid in ids:
                    if mid in s:
                        assert np.abs(s[mid] - d[mid]).max() < 1e-4, (name, cam.key, mid)
                        # the window prediction's correction (72 rim points, facing marks)
                        assert np.abs(s[mid] - preds[mid].correction).max() < 1e-4
                        checked += 1
                    else:
                        assert not preds[mid].facing
    assert checked > 0
    assert CORRECTION_RIM_SAMPLES < 72


def test_corrections_at_reports_the_shift_and_corrected_applies_it() -> None:
    station = real_stations.bonnet()
    recipe = station.recipes[0]
    T0 = recipe.T_rf_from_pf0.matrix
    cams = [c for c in view_cameras(station) if sighted_marks(recipe, c.view, c.camera_id)]
    asked = [(c, sighted_marks(recipe, c.view, c.camera_id)) for c in cams]
    at0 = perspective_corrections(asked, recipe, T0)
    uv0 = np.array([100.0, 200.0])
    groups = []
    for (cam, ids), corr in zip(asked, at0, strict=True):
        dets = [MarkDetection(mark_id=m, found=True, uv=uv0 + corr[m], uv_ellipse=uv0,
                              correction=corr[m]) for m in ids if m in corr]
        dets.append(MarkDetection.missing(ids[0], "not found"))  # passed through untouched
        groups.append((cam, dets))
    same, shift0 = corrections_at(groups, recipe, T0)
    assert shift0 < 1e-9
    T1 = displaced(recipe, 0.8)
    corrs, shift = corrections_at(groups, recipe, T1)
    at1 = perspective_corrections(asked, recipe, T1)
    expected = max(float(np.linalg.norm(a[m] - b[m])) for a, b in zip(at0, at1, strict=True)
                   for m in a)
    assert shift == pytest.approx(expected, abs=1e-12) and shift > 1e-3
    moved = corrected(groups, corrs)
    again, shift_again = recorrect(groups, recipe, T1)  # the two steps in one
    assert shift_again == shift
    for (_, dets), out, c1 in zip(groups, moved, at1, strict=True):
        assert out[-1] is dets[-1]
        for d, m in zip(dets[:-1], out[:-1], strict=True):
            np.testing.assert_allclose(m.uv, uv0 + c1[d.mark_id], atol=1e-12)
            np.testing.assert_allclose(m.correction, c1[d.mark_id], atol=1e-12)
    for out, out_again in zip(moved, again, strict=True):
        for m, m2 in zip(out, out_again, strict=True):
            assert m.uv is None if m2.uv is None else np.array_equal(m.uv, m2.uv)
