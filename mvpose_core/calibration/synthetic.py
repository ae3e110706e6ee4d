"""Calibration scenes with known truth: robot poses around a board, exact and noisy detections."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, apply, compose, invert, make_transform, zyx_to_matrix


@dataclass(frozen=True)
class CalibScene:
    """A rig of cameras (first = reference CF0), a board and robot poses, all with true values.

    mount "robot": the rig is on the flange, X = T_gf_from_cf0, Y = T_rf_from_bf.
    mount "fixed": the rig is fixed in the cell and the board on the flange,
    X = T_rf_from_cf0, Y = T_gf_from_bf.
    """

    mount: str
    board: BoardSpec
    cameras: dict[str, CameraModel]
    T_cfc_from_cf0: dict[str, Array]
    X: Array
    Y: Array
    robot_poses: dict[str, Array]  # T_rf_from_gf by sample id

    def T_cf_from_bf(self, camera_id: str, sid: str) -> Array:
        A = self.robot_poses[sid]
        M = invert(A) if self.mount == "robot" else A
        return compose(self.T_cfc_from_cf0[camera_id], invert(self.X), M, self.Y)

    def observe(
        self, rng: np.random.Generator, noise_px: float, min_corners: int = 6
    ) -> dict[str, dict[str, Detection | None]]:
        """Detections camera → sample id (None where fewer than ``min_corners`` are in view),
        with Gaussian pixel noise of ``noise_px`` per coordinate."""
        return {
            cid: {
                sid: observe_board(
                    self.board, cam, self.T_cf_from_bf(cid, sid), rng, noise_px, min_corners
                )
                for sid in self.robot_poses
            }
            for cid, cam in self.cameras.items()
        }


def observe_board(
    board: BoardSpec,
    cam: CameraModel,
    T_cf_from_bf: Array,
    rng: np.random.Generator,
    noise_px: float,
    min_corners: int = 6,
) -> Detection | None:
    """What a detector would report: projected corners plus noise; chessboards and circle grids
    are found whole or not at all, ChArUco corners one by one."""
    exact = exact_detection(board, cam, T_cf_from_bf, min_corners)
    if exact is None:
        return None
    noise = rng.normal(0.0, noise_px, exact.uv.shape)
    return Detection(exact.ids, exact.uv + noise)


def exact_detection(
    board: BoardSpec, cam: CameraModel, T_cf_from_bf: Array, min_corners: int = 6
) -> Detection | None:
    """The corners in view, projected without noise (None when the board would not be found)."""
    p = apply(T_cf_from_bf, board.object_points)
    ok = p[:, 2] > 1.0
    uv = np.full((p.shape[0], 2), -1e9)
    uv[ok] = cam.project(p[ok])
    ok &= cam.in_image(uv, margin=5.0)
    ids = np.flatnonzero(ok)
    if board.kind != "charuco" and ids.size != board.n_corners:
        return None
    if ids.size < min_corners:
        return None
    return Detection(ids.astype(np.int64), uv[ids])


@dataclass(frozen=True)
class StationScene:
    """Fixed cameras over a work area and board placements with their true poses in RF."""

    board: BoardSpec
    cameras: dict[str, CameraModel]
    T_rf_from_cf: dict[str, Array]
    T_rf_from_bf: dict[str, Array]

    def observe(
        self, rng: np.random.Generator, noise_px: float
    ) -> dict[str, dict[str, Detection | None]]:
        return {
            cid: {
                sid: observe_board(
                    self.board, cam, compose(invert(self.T_rf_from_cf[cid]), T), rng, noise_px
                )
                for sid, T in self.T_rf_from_bf.items()
            }
            for cid, cam in self.cameras.items()
        }


def make_station_scene(
    rng: np.random.Generator,
    n_placements: int = 12,
    n_cameras: int = 3,
    spacing_mm: float = 300.0,
    height_mm: float = 1300.0,
    board: BoardSpec | None = None,
    camera: CameraModel | None = None,
) -> StationScene:
    """Cameras in a row ``spacing_mm`` apart, ``height_mm`` above the floor of RF, looking down
    and slightly inwards; each placement is seen by at least two cameras."""
    board = board or BoardSpec("chessboard", 11, 8, 35.0)
    cam = camera or lab_camera()
    xs = (np.arange(n_cameras) - (n_cameras - 1) / 2) * spacing_mm
    cams = {f"cam{k + 1}": cam for k in range(n_cameras)}
    T_rf_from_cf = {}
    for k, x in enumerate(xs):
        # Looking down (CF z = -RF z), toed in towards the middle of the row.
        tilt = np.degrees(np.arctan2(x, height_mm)) * 0.5
        R = zyx_to_matrix(90.0, 0.0, 180.0) @ zyx_to_matrix(0.0, 0.0, tilt)
        T_rf_from_cf[f"cam{k + 1}"] = make_transform(R, [1500.0 + x, 200.0, height_mm])
    centre = board.object_points.mean(axis=0)
    placements: dict[str, Array] = {}
    tries = 0
    while len(placements) < n_placements:
        tries += 1
        if tries > 500 * n_placements:
            raise ValueError("make_station_scene: cannot place the board in two cameras at once")
        R = zyx_to_matrix(
            rng.uniform(-180, 180), rng.uniform(-25, 25), 180.0 + rng.uniform(-25, 25)
        )
        pos = np.array(
            [
                1500.0 + rng.uniform(xs[0], xs[-1]),
                200.0 + rng.normal(0, 0.05 * height_mm),
                rng.uniform(0, 0.25 * height_mm),
            ]
        )
        T = make_transform(R, pos - R @ centre)
        seen = [exact_detection(board, cams[c], compose(invert(T_rf_from_cf[c]), T)) for c in cams]
        if sum(d is not None for d in seen) >= 2:
            placements[f"{len(placements) + 1:03d}"] = T
    return StationScene(board, cams, T_rf_from_cf, placements)


def lab_camera(width: int = 2048, height: int = 2048, f: float = 2909.1) -> CameraModel:
    """A camera like the paper's (16 mm lens, 5.5 µm pixels) with mild distortion."""
    return CameraModel(
        f,
        f,
        (width - 1) / 2 + 3.2,
        (height - 1) / 2 - 2.7,
        width,
        height,
        (-0.08, 0.12, 0.0002, -0.0001, 0.0),
    )


def make_scene(
    rng: np.random.Generator,
    n_poses: int = 15,
    mount: str = "robot",
    stereo: bool = True,
    board: BoardSpec | None = None,
    camera: CameraModel | None = None,
    distance_mm: tuple[float, float] = (650.0, 900.0),
    max_tilt_deg: float = 35.0,
    baseline_mm: float = 300.0,
    converge_mm: float = 1000.0,
) -> CalibScene:
    """Views of the board from a cone of directions (tilt ≤ ``max_tilt_deg``) and random roll,
    at distances in ``distance_mm``, aimed at the board centre with a little scatter."""
    board = board or BoardSpec("chessboard", 11, 8, 35.0)
    cam = camera or lab_camera()
    cameras = {"left": cam}
    rel = {"left": np.eye(4)}
    if stereo:
        cameras["right"] = cam
        # Lab rig by default: 300 mm baseline, the right camera toed in to cross the left
        # camera's axis at 1 m.
        toe = -np.degrees(np.arctan2(baseline_mm, converge_mm))
        rel["right"] = invert(make_transform(zyx_to_matrix(0, toe, 0), [baseline_mm, 0, 0]))
    if mount == "robot":
        X = make_transform(zyx_to_matrix(90.0, 0.5, -1.0), [12.0, 118.0, 176.0])  # T_gf_from_cf0
        Y = board_in_front()  # flat on a table, printed face up (BF z points down)
    else:
        X = make_transform(
            zyx_to_matrix(180.0, 20.0, 180.0), [2200.0, 300.0, 900.0]
        )  # T_rf_from_cf0
        Y = make_transform(zyx_to_matrix(0.0, 0.0, 180.0), [-100.0, -80.0, 120.0])  # T_gf_from_bf
    poses = view_poses(rng, mount, board, cameras, rel, X, Y, n_poses, distance_mm, max_tilt_deg)
    return CalibScene(mount, board, cameras, rel, X, Y, poses)


def view_poses(
    rng: np.random.Generator,
    mount: str,
    board: BoardSpec,
    cameras: dict[str, CameraModel],
    rel: dict[str, Array],
    X: Array,
    Y: Array,
    n_poses: int,
    distance_mm: tuple[float, float],
    max_tilt_deg: float,
) -> dict[str, Array]:
    """Flange poses ``T_rf_from_gf`` from which every camera sees the board: the reference camera
    looks at the board centre (with a little scatter) from a cone of directions (tilt up to
    ``max_tilt_deg``, random roll) at distances in ``distance_mm``."""
    centre = board.object_points.mean(axis=0)
    poses: dict[str, Array] = {}
    k = 0
    while len(poses) < n_poses:
        k += 1
        if k > 200 * n_poses:
            raise ValueError(f"could not place {n_poses} views with the board in every camera")
        tilt = np.radians(rng.uniform(0.0, max_tilt_deg))
        az = rng.uniform(0.0, 2 * np.pi)
        d = rng.uniform(*distance_mm)
        # Camera looks along -view_dir at the board centre (+ scatter), from the board's front side.
        view_dir = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        aim = centre + np.r_[rng.normal(0.0, 15.0, 2), 0.0]
        c_bf = aim + d * view_dir
        z = aim - c_bf
        z /= np.linalg.norm(z)
        roll = rng.uniform(-np.pi, np.pi)
        up = np.array([np.cos(roll), np.sin(roll), 0.0])
        x = np.cross(up, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        T_bf_from_cf0 = make_transform(np.stack([x, y, z], axis=1), c_bf)
        T_cf0_from_bf = invert(T_bf_from_cf0)
        if mount == "robot":
            A = compose(Y, T_bf_from_cf0, invert(X))  # T_rf_from_gf
        else:
            A = compose(X, T_cf0_from_bf, invert(Y))
        sid = f"{len(poses) + 1:03d}"
        scene = CalibScene(mount, board, cameras, rel, X, Y, {sid: A})
        seen = [exact_detection(board, cameras[c], scene.T_cf_from_bf(c, sid)) for c in cameras]
        if all(d is not None for d in seen):
            poses[sid] = A
    return poses


def with_robot_error(
    rng: np.random.Generator, poses: dict[str, Array], mm: float, deg: float
) -> dict[str, Array]:
    """The flange poses as a robot reports them: each off by a random rotation (``deg`` 1σ per
    axis, about the flange axes) and translation (``mm`` 1σ per axis)."""
    return {
        sid: A
        @ make_transform(
            Rotation.from_rotvec(rng.normal(0.0, np.radians(deg), 3)).as_matrix(),
            rng.normal(0.0, mm, 3),
        )
        for sid, A in poses.items()
    }


def board_in_front(reach_mm: float = 1300.0) -> Array:
    """``T_rf_from_bf`` of a board flat on a table in front of the robot, printed face up."""
    return make_transform(zyx_to_matrix(30.0, 180.0, 0.0), [reach_mm, 150.0, -50.0])


def station_placements(
    rng: np.random.Generator,
    board: BoardSpec,
    cameras: dict[str, CameraModel],
    T_rf_from_cf: dict[str, Array],
    n_placements: int,
    max_tilt_deg: float = 20.0,
    min_corners: int = 12,
) -> dict[str, Array]:
    """Board placements ``T_rf_from_bf`` for fixed cameras, each seen by two or more of them:
    aimed where a random pair's optical axes pass closest to each other, facing the pair (the
    bisector of their viewing directions, tilted up to ``max_tilt_deg``, any roll). Pairs whose
    axes never meet in front of both cameras are skipped; ``ValueError`` when no pair can share
    a placement."""
    ids = list(cameras)
    pairs = [(a, b) for i, a in enumerate(ids) for b in ids[i + 1 :]]
    aims: list[tuple[Array, Array]] = []
    for a, b in pairs:
        pa, pb = T_rf_from_cf[a][:3, 3], T_rf_from_cf[b][:3, 3]
        da, db = T_rf_from_cf[a][:3, 2], T_rf_from_cf[b][:3, 2]
        # Closest points of the two axes pa + s·da and pb + t·db.
        M = np.array([[da @ da, -(da @ db)], [da @ db, -(db @ db)]])
        if abs(np.linalg.det(M)) < 1e-9:
            continue
        s, t = np.linalg.solve(M, [(pb - pa) @ da, (pb - pa) @ db])
        if s <= 0 or t <= 0:
            continue
        facing = -(da + db)
        aims.append(((pa + s * da + pb + t * db) / 2, facing / np.linalg.norm(facing)))
    if not aims:
        raise ValueError("no two cameras look at a common point: no board placement can link them")
    centre = board.object_points.mean(axis=0)
    placements: dict[str, Array] = {}
    tries = 0
    while len(placements) < n_placements:
        tries += 1
        if tries > 400 * n_placements:
            raise ValueError(
                f"only {len(placements)} of {n_placements} board placements are seen by two "
                "cameras at once; try a smaller board"
            )
        aim, facing = aims[rng.integers(len(aims))]
        tilt = Rotation.from_rotvec(
            np.radians(rng.uniform(0.0, max_tilt_deg)) * _unit_normal_to(facing, rng)
        )
        z = -tilt.apply(facing)  # the board's z points away from the cameras (printed face up)
        x = np.cross(_unit_normal_to(z, rng), z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z], axis=1)
        pos = aim + rng.normal(0.0, 50.0, 3)
        T = make_transform(R, pos - R @ centre)
        seen = [
            exact_detection(board, cameras[c], compose(invert(T_rf_from_cf[c]), T), min_corners)
            for c in ids
        ]
        if sum(d is not None for d in seen) >= 2:
            placements[f"{len(placements) + 1:03d}"] = T
    return placements


def _unit_normal_to(v: Array, rng: np.random.Generator) -> Array:
    """A random unit vector perpendicular to ``v``."""
    w = np.cross(v, rng.normal(size=3))
    return w / np.linalg.norm(w)
