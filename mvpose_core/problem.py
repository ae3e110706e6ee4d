"""A pose problem checked at the public edge and packed for the solver: one row per observation.

:func:`build_problem` validates what :func:`mvpose_core.estimate.estimate_pose` receives (shapes,
NaN, unknown cameras or marks, duplicates, too few or collinear marks) and raises
:class:`PoseInputError` naming the problem; it then gathers every observation's camera pose,
intrinsics and mark position into a :class:`~mvpose_core.refine.Packed` array set. The common
path is vectorised; the per-observation loop only runs to name a culprit.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mvpose_core.cache import IdentityCache
from mvpose_core.initial import COLLINEAR_RATIO, collinearity
from mvpose_core.reasons import Reason
from mvpose_core.refine import Array, Packed
from mvpose_core.scene import ViewCamera
from mvpose_core.triangulate import group_matrix


class PoseInputError(ValueError):
    """The estimator refuses its input; ``reason`` is the gate code the server reports."""

    def __init__(self, message: str, reason: Reason = Reason.BAD_INPUT) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Observation:
    """One detected mark centre in one image: distorted pixel ``uv`` ``[2]``."""

    view: int
    camera_id: str
    mark_id: str
    uv: np.ndarray
    sigma_px: float | None = None  # per-observation σ; None = the call's sigma_px
    #: the mark's next candidates in this image (``[2]`` each, best first): the robust rule
    #: (mvpose_core.robust) tries them when ``uv`` disagrees with the rest
    alternates: tuple[np.ndarray, ...] = ()
    #: the detection's relative centre variance, fit_residual_px² / radius_px: a smaller or
    #: fainter mark's centre, or one whose rim is disturbed, is noisier. ``mvpose_core.measure``
    #: turns it into ``sigma_px`` (docs/engine.md, "Uncertainty model"); None = no figure
    #: (synthetic observations)
    centre_variance: float | None = None

    @property
    def key(self) -> tuple[int, str, str]:
        return (self.view, self.camera_id, self.mark_id)

    def but(self, **changes: object) -> Observation:
        """The observation with some fields changed (as ``dataclasses.replace``, without its
        generic machinery: this runs per observation and solve in the robust rule)."""
        out = object.__new__(Observation)
        out.__dict__.update(self.__dict__, **changes)
        return out


@dataclass(frozen=True)
class Lenses:
    """What a camera list fixes apart from the poses: the index of each (view, camera_id), the
    lens of each camera as arrays, which cameras lead their rig."""

    index: dict[tuple[int, str], int]
    f: Array  # [C, 2]
    c: Array  # [C, 2]
    k: Array  # [C, 8]
    left: NDArray[np.bool_]  # [C] first camera of its rig
    #: (K, distortion) for OpenCV when every camera has the same intrinsics and distortion
    lens: tuple[Array, Array] | None

    @classmethod
    def of(cls, cameras: Sequence[ViewCamera]) -> Lenses:
        index = {(c.view, c.camera_id): i for i, c in enumerate(cameras)}
        if len(index) != len(cameras):
            keys = [c.key for c in cameras]
            raise PoseInputError(f"a camera is listed twice: {sorted(set(keys), key=keys.index)}")
        m = [c.model for c in cameras]
        lens = {(x.fx, x.fy, x.cx, x.cy, tuple(x.dist) + (0.0,) * (8 - len(x.dist))) for x in m}
        one = (m[0].K, m[0].dist_array) if len(lens) == 1 else None
        out = cls(
            index=index,
            f=np.array([(x.fx, x.fy) for x in m]),
            c=np.array([(x.cx, x.cy) for x in m]),
            k=np.array([tuple(x.dist) + (0.0,) * (8 - len(x.dist)) for x in m]),
            left=np.array([c.rig_position == 0 for c in cameras]),
            lens=one,
        )
        # shared by every table and problem packed with these lenses
        for a in (out.f, out.c, out.k, out.left, *(one or ())):
            a.flags.writeable = False
        return out


_LENSES: IdentityCache[Lenses] = IdentityCache(16)


def _lenses(cameras: Sequence[ViewCamera]) -> Lenses:
    """:meth:`Lenses.of`, remembered for the same lens model objects at the same places.

    A robot-mounted camera re-posed to the robot's actual flange pose
    (:func:`mvpose_core.scene.repose`) keeps its lens model object, so its lenses are found
    again although the camera object is new.
    """
    return _LENSES.get(tuple(c.model for c in cameras),
                       tuple((c.view, c.camera_id, c.rig_position) for c in cameras),
                       lambda: Lenses.of(cameras))


@dataclass(frozen=True)
class CameraTable:
    """Every view camera's pose and lens as arrays, indexed by (view, camera_id)."""

    lenses: Lenses
    R_cf_from_rf: Array  # [C, 3, 3]
    t_cf_from_rf: Array  # [C, 3]
    T_rf_from_cf: Array  # [C, 4, 4]

    @property
    def index(self) -> dict[tuple[int, str], int]:
        return self.lenses.index

    @property
    def left(self) -> NDArray[np.bool_]:
        return self.lenses.left

    @property
    def lens(self) -> tuple[Array, Array] | None:
        return self.lenses.lens

    @classmethod
    def of(cls, cameras: Sequence[ViewCamera], lenses: Lenses | None = None) -> CameraTable:
        lenses = lenses if lenses is not None else Lenses.of(cameras)
        T = np.asarray([c.T_rf_from_cf for c in cameras], dtype=float)
        if T.shape != (len(cameras), 4, 4) or not np.all(np.isfinite(T)):
            raise PoseInputError("every camera needs a finite 4x4 T_rf_from_cf")
        R = np.transpose(T[:, :3, :3], (0, 2, 1))
        return cls(lenses, R, -np.einsum("cij,cj->ci", R, T[:, :3, 3]), T)

    def rows(self, ci: NDArray[np.intp], p_pf: Array, uv: Array, weight: Array) -> Packed:
        k = self.lenses.k[ci]
        return Packed(
            self.R_cf_from_rf[ci], self.t_cf_from_rf[ci], p_pf, uv, weight,
            self.lenses.f[ci], self.lenses.c[ci], k, bool(np.any(k[:, 5:])), self.lenses.lens,
        )  # fmt: skip


@dataclass(frozen=True)
class Problem:
    """Validated observations, packed (``pk``) with the indices the starts need."""

    pk: Packed
    ci: NDArray[np.intp]  # [N] camera index of each observation (into ``cameras``)
    mi: NDArray[np.intp]  # [N] mark index of each observation (into ``mark_ids``)
    mark_ids: list[str]
    P_marks: Array  # [M, 3] distinct marks in PF
    table: CameraTable
    keys: list[tuple[int, str, str]]
    centres_rf: Array  # [N, 3] centre of each observation's camera in RF
    R_rf_from_cf: Array  # [N, 3, 3] rotation of each observation's camera
    max_views_per_mark: int  # most observations of one mark (≥ 2: triangulation can start)
    mark_rows: Array  # [M, N] one-hot: which observations are of mark m (triangulation)


_TABLES: IdentityCache[CameraTable] = IdentityCache(16)


def _camera_table(cameras: Sequence[ViewCamera]) -> CameraTable:
    """:meth:`CameraTable.of`, remembered for the last few camera lists.

    A station measures with the same posed cameras trigger after trigger; gathering them into
    arrays is a fifth of an estimate's time. An entry is used only for the very same (frozen)
    camera objects, so a new flange pose or calibration never meets a stale table; cameras
    re-posed to a new flange pose find their lenses again and gather only their poses.
    """
    return _TABLES.get(tuple(cameras), None, lambda: CameraTable.of(cameras, _lenses(cameras)))


def _marks(marks_pf: Mapping[str, np.ndarray], ids: Sequence[str]) -> Array:
    try:
        P = np.array([marks_pf[m] for m in ids], dtype=float)
        if P.shape == (len(ids), 3) and np.all(np.isfinite(P)):
            return P
    except (KeyError, ValueError, TypeError):
        pass
    for m in ids:  # slow path, to name the culprit
        if m not in marks_pf:
            raise PoseInputError(f"observation names unknown mark {m!r}")
        p = np.asarray(marks_pf[m], dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PoseInputError(
                f"mark {m!r}: position must be 3 finite values (mm), got {p.tolist()}"
            )
    raise PoseInputError(f"mark positions for {list(ids)} are not a [M, 3] array")  # unreachable


def _name(key: tuple[int, str, str]) -> str:
    return f"observation v{key[0]}/{key[1]}/{key[2]}"


@dataclass(frozen=True)
class _Layout:
    """What a problem's structure fixes: which camera and mark each row has, the packed lens
    and mark arrays, and that the marks fix a pose. Neither the camera poses nor the pixels
    are part of it."""

    keys: list[tuple[int, str, str]]
    ci: NDArray[np.intp]
    mi: NDArray[np.intp]
    mark_ids: list[str]
    P: Array  # [M, 3]
    template: Packed  # zero pixels, unit weights (poses: those of the table it was made with)
    max_views_per_mark: int
    mark_rows: Array  # [M, N]


@dataclass(frozen=True)
class _Posed:
    """A layout's rows at one camera table's poses."""

    template: Packed
    centres_rf: Array  # [N, 3]
    R_rf_from_cf: Array  # [N, 3, 3]


_LAYOUTS: IdentityCache[_Layout] = IdentityCache(32)
_POSED: IdentityCache[_Posed] = IdentityCache(32)


def _layout(
    table: CameraTable, keys: list[tuple[int, str, str]], marks_pf: Mapping[str, np.ndarray]
) -> tuple[_Layout, _Posed]:
    """The layout of ``keys`` and its rows at ``table``'s poses, remembered for the last few.

    A station sees the same marks in the same cameras trigger after trigger; checking and
    packing that structure is half of :func:`build_problem`. A layout is used only for the
    very same lenses object, the same observation keys and the same mark positions; its rows at
    the poses of a camera table only for that very table (a robot's new flange pose is a new
    table, which gathers its camera poses row by row and nothing else).
    """
    try:
        P = _marks(marks_pf, sorted({m for _, _, m in keys}))
    except PoseInputError:  # built (and refused, in the order of its checks) uncached
        layout = _new_layout(table, keys, marks_pf)
        return layout, _posed(table, layout)
    layout = _LAYOUTS.get((table.lenses,), (tuple(keys), P.tobytes()),
                          lambda: _new_layout(table, keys, marks_pf))
    return layout, _POSED.get((table, layout), None, lambda: _posed(table, layout))


def _posed(table: CameraTable, layout: _Layout) -> _Posed:
    ci = layout.ci
    template = layout.template.with_poses(table.R_cf_from_rf[ci], table.t_cf_from_rf[ci])
    T = table.T_rf_from_cf[ci]
    posed = _Posed(template, T[:, :3, 3].copy(), T[:, :3, :3].copy())
    # Every problem at these poses shares these arrays: an in-place change would corrupt the
    # next trigger's, so it raises instead.
    for a in (template.R_cf_from_rf, template.t_cf_from_rf, posed.centres_rf,
              posed.R_rf_from_cf):
        a.flags.writeable = False
    return posed


def _new_layout(
    table: CameraTable, keys: list[tuple[int, str, str]], marks_pf: Mapping[str, np.ndarray]
) -> _Layout:
    n = len(keys)
    cams = [table.index.get((v, c)) for v, c, _ in keys]
    if None in cams:
        v, c, m = keys[cams.index(None)]
        raise PoseInputError(f"{_name((v, c, m))}: no camera v{v}/{c} in this station")
    if len(set(keys)) != n:
        dup = next(k for i, k in enumerate(keys) if k in keys[:i])
        raise PoseInputError(f"{_name(dup)}: the same mark is observed twice in one image")
    mark_ids = sorted({m for _, _, m in keys})
    if len(mark_ids) < 3:
        raise PoseInputError(
            f"too few marks: a pose needs at least 3 distinct marks, got {len(mark_ids)} "
            f"{mark_ids}",
            Reason.TOO_FEW_MARKS,
        )
    P = _marks(marks_pf, mark_ids)
    ratio = collinearity(P)
    if ratio < COLLINEAR_RATIO:
        raise PoseInputError(
            f"marks {mark_ids} are collinear (spread ratio {ratio:.1e}): rotation about their "
            "line is undetermined",
            Reason.POSE_NOT_DETERMINED,
        )
    pos = {m: i for i, m in enumerate(mark_ids)}
    mi = np.array([pos[m] for _, _, m in keys], dtype=np.intp)
    ci = np.array(cams, dtype=np.intp)
    template = table.rows(ci, P[mi], np.zeros((n, 2)), np.ones(n))
    layout = _Layout(list(keys), ci, mi, mark_ids, P, template, int(np.bincount(mi).max()),
                     group_matrix(mi, len(mark_ids)))
    # Every problem with this layout shares these arrays: an in-place change would corrupt the
    # next trigger's, so it raises instead.
    for a in (*vars(template).values(), ci, mi, P, layout.mark_rows):
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    return layout


def build_problem(
    observations: Sequence[Observation],
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    sigma_px: float,
) -> Problem:
    """Validate and pack; every refusal is a :class:`PoseInputError` naming the problem."""
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise PoseInputError(f"sigma_px must be a positive number of pixels, got {sigma_px}")
    table = _camera_table(cameras)
    n = len(observations)
    keys = [(o.view, o.camera_id, o.mark_id) for o in observations]
    layout, posed = _layout(table, keys, marks_pf)
    try:
        uv = np.array([o.uv for o in observations], dtype=float).reshape(n, 2)
        ok = bool(np.isfinite(uv).all())
    except (ValueError, TypeError):
        ok = False
    if not ok:
        for key, o in zip(keys, observations, strict=True):
            u = np.asarray(o.uv, dtype=float)
            if u.shape != (2,):
                raise PoseInputError(f"{_name(key)}: uv must have shape (2,), got {u.shape}")
            if not np.all(np.isfinite(u)):
                raise PoseInputError(
                    f"{_name(key)}: uv contains NaN or infinite values {u.tolist()}"
                )
    weight = np.full(n, 1.0 / sigma_px)
    for i, o in enumerate(observations):
        if o.sigma_px is not None:
            if not (np.isfinite(o.sigma_px) and o.sigma_px > 0):
                raise PoseInputError(f"{_name(keys[i])}: sigma_px must be > 0, got {o.sigma_px}")
            weight[i] = 1.0 / o.sigma_px
    return Problem(posed.template.with_measurements(uv, weight), layout.ci, layout.mi,
                   layout.mark_ids, layout.P, table, layout.keys, posed.centres_rf,
                   posed.R_rf_from_cf, layout.max_views_per_mark, layout.mark_rows)


def pack_layout(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    layout: Sequence[tuple[int, str, str]],
    objective: str = "all",
) -> tuple[Packed, NDArray[np.intp]]:
    """Pack a layout of (view, camera_id, mark_id) with zero pixels; rows kept by ``objective``."""
    table = CameraTable.of(cameras)
    ci = np.empty(len(layout), dtype=np.intp)
    for n, (v, cid, _m) in enumerate(layout):
        if (v, cid) not in table.index:
            raise PoseInputError(f"layout names unknown camera v{v}/{cid}")
        ci[n] = table.index[(v, cid)]
    p = _marks(marks_pf, [m for _, _, m in layout])
    rows = np.arange(len(layout)) if objective == "all" else np.flatnonzero(table.left[ci])
    return table.rows(ci[rows], p[rows], np.zeros((rows.size, 2)), np.ones(rows.size)), rows
