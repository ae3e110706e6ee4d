"""Issue 26, item 2: the reported 1σ holds on every kind of station, and a mark seen steeply
near the frame edge is measured through the station path as well as by the detector alone.

Stations (tests/mvpose_core/real_stations.py): the bonnet (three fixed cameras, one tilted 35°,
five mark diameters), the front floor (a robot-mounted stereo rig in two views) and the compact
panel (four fixed cameras; one tilted 35° with a 12 mm lens on 2048², k1 = −0.11, sees a 14 mm
mark of ~25 px radius at v ≈ 1620). Rendered images (clutter on), seeded; docs/engine.md has the
figures of ``python -m bench.station_uncertainty``.
"""

from __future__ import annotations

import numpy as np
import pytest
from real_stations import bonnet, compact, floor

from mvpose_core.detect import (
    DetectOptions,
    correct_centres,
    detect_marks,
    detect_marks_many,
    predict_marks,
    recorrect,
)
from mvpose_core.measure import measure
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.robust import observations_of
from mvpose_core.scene import view_cameras
from mvpose_core.simulation.rendered import displaced_about_marks, rendered_trial

FAST = RenderOptions(supersample=8, clutter=True)


def _rms(x: list[float] | np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_the_steep_station_is_what_the_issue_describes() -> None:
    st = compact()
    rec = st.recipe()
    steep = next(c for c in view_cameras(st) if c.camera_id == "steep")
    assert (steep.model.width, steep.model.height) == (2048, 2048)
    (p,) = predict_marks(steep, rec, rec.T_rf_from_pf0.matrix)
    assert p.mark.mark_id == "M2" and p.diameter_mm == 14.0
    assert 1600.0 < p.uv[1] < 1640.0 and 23.0 < p.ellipse.radius < 27.0
    # seen 35° off its normal: the rim is an ellipse of axis ratio ≈ cos 35°
    assert p.ellipse.axis_ratio == pytest.approx(np.cos(np.radians(35.0)), abs=0.02)


def test_the_station_path_measures_the_steep_mark_as_the_detector_alone() -> None:
    """The pipeline's path (windows at the taught pose with the correction there, the pose,
    the correction again at the estimate when it moved by more than 0.01 px) against
    detect_marks + correct_centres at the true pose, on the same images."""
    st = compact()
    rec = st.recipe()
    cams = view_cameras(st)
    prior = rec.T_rf_from_pf0.matrix
    rng = np.random.default_rng(21)
    station: dict[tuple[str, str], list[np.ndarray]] = {}
    direct: dict[tuple[str, str], list[np.ndarray]] = {}
    for _ in range(8):
        T = displaced_about_marks(rec, rng, 8.0, 0.8)
        rendered = [render_view(vc, rec, T, rng, FAST) for vc in cams]
        frames = [(r.image, vc) for r, vc in zip(rendered, cams, strict=True)]
        found = detect_marks_many(frames, rec, prior, DetectOptions(correct_perspective=True))
        groups = [(vc, d) for (_, vc), d in zip(frames, found, strict=True)]
        obs = [o for vc, d in groups for o in observations_of(1, {vc.camera_id: d})]
        m = measure(st, rec, obs, cameras=cams)
        moved, shift = recorrect(groups, rec, m.T_rf_from_pf)
        final = moved if shift > 0.01 else [d for _, d in groups]
        for r, vc, dets in zip(rendered, cams, final, strict=True):
            alone = correct_centres(detect_marks(r.image, vc, rec, prior), vc, rec, T)
            for a, b in zip(dets, alone, strict=True):
                assert a.found and b.found, (vc.key, a.reason, b.reason)
                key = (vc.camera_id, a.mark_id)
                station.setdefault(key, []).append(a.uv - r.centres[a.mark_id])
                direct.setdefault(key, []).append(b.uv - r.centres[b.mark_id])
    s, d = _rms(station[("steep", "M2")]), _rms(direct[("steep", "M2")])
    assert s < 0.02 and s < 1.2 * d, (s, d)
    every_s = _rms(np.concatenate([np.array(v) for v in station.values()]))
    every_d = _rms(np.concatenate([np.array(v) for v in direct.values()]))
    assert every_s < 1.2 * every_d, (every_s, every_d)


@pytest.mark.parametrize("build,body_mm", [(bonnet, 1700.0), (floor, 1700.0), (compact, 0.0)])
def test_reported_sigma_holds_on_every_kind_of_station(build, body_mm) -> None:  # type: ignore[no-untyped-def]
    """Actual error / reported 1σ at the grasp frame, RMS over 24 rendered triggers: within
    0.7–1.4 for rotation and translation (an RMS of 24 three-axis errors is known to ~8 %)."""
    st = build(body_mm)
    rec = st.recipe()
    rng = np.random.default_rng(26)
    actual, reported = [], []
    for _ in range(24):
        r = rendered_trial(st, rec, displaced_about_marks(rec, rng, 5.0, 0.5), rng, FAST)
        m = r.measurement
        assert m is not None and m.gate.ok, r.refused or m
        actual.append((r.rot_err_deg, r.trans_err_mm))
        reported.append((m.sigma_rot_deg, m.sigma_trans_mm))
    a, b = np.array(actual), np.array(reported)
    ratio = [_rms(a[:, k]) / _rms(b[:, k]) for k in (0, 1)]
    assert 0.7 < ratio[0] < 1.4 and 0.7 < ratio[1] < 1.4, (st.name, ratio)
