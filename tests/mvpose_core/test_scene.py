"""Scene geometry: camera poses per view (paper eq. 11-12) and projected recipe marks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvpose_core.scene import project_recipe_marks, sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.transforms import apply, compose, invert, xyzwpr_to_matrix

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"


def test_robot_views_follow_hand_eye_chain() -> None:
    st = load_station(STATIONS / "lab.yaml")
    cams = view_cameras(st)
    assert [c.key for c in cams] == ["v1/left", "v1/right", "v2/left", "v2/right"]
    rig = st.rig("stereo")
    T_gf_from_cf = compose(rig.T_gf_from_rig.matrix, rig.cameras[0].T_rig_from_cf.matrix)
    # Paper eq. 12: T_cf1_from_cfi = T_cf_from_gf · T_gf1_from_gfi · T_gf_from_cf
    T_rf_from_gf = {v.id: v.T_rf_from_gf.matrix for v in st.views}
    paper = compose(invert(T_gf_from_cf), invert(T_rf_from_gf[1]), T_rf_from_gf[2], T_gf_from_cf)
    ours = compose(invert(cams[0].T_rf_from_cf), cams[2].T_rf_from_cf)
    assert np.allclose(paper, ours, atol=1e-9)


def test_actual_flange_pose_overrides_taught_pose() -> None:
    st = load_station(STATIONS / "lab.yaml")
    moved = compose(st.view(2).T_rf_from_gf.matrix, xyzwpr_to_matrix([1, 0, 0, 0, 0, 0]))
    cams = view_cameras(st, flange_poses={2: moved})
    base = view_cameras(st)
    assert np.allclose(cams[0].T_rf_from_cf, base[0].T_rf_from_cf)
    assert not np.allclose(cams[2].T_rf_from_cf, base[2].T_rf_from_cf)


def test_sighted_marks_project_into_the_image_in_front() -> None:
    for name in ["lab", "station1", "station2"]:
        st = load_station(STATIONS / f"{name}.yaml")
        rec = st.recipe()
        T = rec.T_rf_from_pf0.matrix
        seen = set()
        for cam in view_cameras(st):
            for pm in project_recipe_marks(cam, rec, T):
                assert pm.depth_mm > 500
                assert cam.model.in_image(pm.uv[None], margin=50).all(), (name, cam.key, pm.mark_id)
                # the mark faces the camera
                assert float(pm.n_cf @ pm.p_cf) < 0
                p_rf = apply(T, np.asarray(rec.marks[rec.mark_index(pm.mark_id)].position))
                assert np.allclose(apply(invert(cam.T_rf_from_cf), p_rf), pm.p_cf)
                seen.add(pm.mark_id)
        assert seen == {m.id for m in rec.marks}


def test_station1_cameras_do_not_overlap() -> None:
    st = load_station(STATIONS / "station1.yaml")
    rec = st.recipe()
    lists = [sighted_marks(rec, 1, c) for c in st.view_camera_ids(1)]
    flat = [m for lst in lists for m in lst]
    assert len(flat) == len(set(flat)) == 8
