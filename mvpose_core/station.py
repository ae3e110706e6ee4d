"""The station description: one typed model, loaded from YAML, used by every part of mvpose.

A station file lists the cameras, the rigs that hold them (on the robot flange or fixed in the
cell), the views (robot flange poses at which a robot-mounted rig takes pictures; a fixed station
has one view with every fixed rig), and the recipes (part types: marks from CAD, which camera sees
which mark in which view, the taught reference pose, grasp frame, tolerances, robot convention).

Poses in the file are written in one of three forms (:class:`Pose`): ``{xyz: [X, Y, Z],
wpr: [W, P, R]}`` in mm and degrees with R = Rz(R)·Ry(P)·Rx(W) (the FANUC convention, see
:mod:`mvpose_core.transforms`); ``{matrix: [[...], [...], [...], [0, 0, 0, 1]]}``, the 4x4
transform row by row in mm; or ``{convention: kuka, values: [X, Y, Z, A, B, C]}`` in any robot
convention's own values and units. Each field that holds a pose is named after the transform it
is: ``T_gf_from_rig`` is the pose of the rig in the flange frame (the hand-eye transform),
``T_rf_from_pf0`` the taught part pose in the robot base.

Every model forbids unknown keys, so a typo stops start-up instead of being ignored.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from mvpose_core.camera import CameraModel
from mvpose_core.drift import DriftOptions
from mvpose_core.plantconfig import PlantConfig
from mvpose_core.shifts import DEFAULT_SHIFTS, Shift, check_shifts, time_zone
from mvpose_core.transforms import (
    Array,
    RobotConvention,
    check_transform,
    from_robot,
    matrix_to_xyzwpr,
    to_robot,
    xyzwpr_to_matrix,
)
from mvpose_core.uncertainty_settings import UncertaintyConfig

Identifier = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)]
Vec3 = tuple[float, float, float]


class StationFileError(ValueError):
    """A station file cannot be used; the message names the file, the field and the value."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Vec4 = tuple[float, float, float, float]
Rows4 = tuple[Vec4, Vec4, Vec4, Vec4]

#: how far a ``matrix`` pose's rotation may be from orthonormal (|R·Rᵀ − I| per element)
MATRIX_TOLERANCE = 1e-6


@lru_cache(maxsize=256)
def _pose_matrix(xyz: Vec3, wpr: Vec3) -> Array:
    # Every trigger asks for the recipe's reference pose several times; a pose is a frozen
    # value, so its matrix is computed once. Read-only, as it is shared.
    T = xyzwpr_to_matrix([*xyz, *wpr])
    T.flags.writeable = False
    return T


@lru_cache(maxsize=256)
def _rows_matrix(rows: Rows4) -> Array:
    T = check_transform(np.array(rows, dtype=float), "matrix", tol=MATRIX_TOLERANCE)
    T.flags.writeable = False
    return T


@lru_cache(maxsize=256)
def _robot_matrix(convention: RobotConvention, values: tuple[float, ...]) -> Array:
    T = from_robot(values, convention)
    T.flags.writeable = False
    return T


class Pose(_Model):
    """A rigid transform in one of three forms; exactly one is given.

    - ``{xyz, wpr}``: translation in mm, rotation as FANUC W P R in degrees (``wpr`` may be left
      out: no rotation);
    - ``{matrix}``: the 4x4 transform, row by row, translation in mm; the rotation must be
      orthonormal to :data:`MATRIX_TOLERANCE` (write 7 or more significant digits) and the last
      row ``[0, 0, 0, 1]``; it is used exactly as written;
    - ``{convention, values}``: a robot convention's pose vector in that convention's units
      (:class:`~mvpose_core.transforms.RobotConvention`: ``abb`` 7 values with a quaternion,
      ``ur`` metres and a rotation vector in radians, the others mm and degrees).

    A pose keeps the form it was written in, so a file read and written again is unchanged.
    """

    xyz: Vec3 | None = None
    wpr: Vec3 | None = None
    rows: Rows4 | None = Field(None, alias="matrix", description="4x4 transform, row-major, mm")
    convention: RobotConvention | None = None
    values: tuple[float, ...] | None = None

    @field_validator("convention", mode="before")
    @classmethod
    def _convention_any_case(cls, v: Any) -> Any:
        return v.lower() if isinstance(v, str) else v

    @model_validator(mode="before")
    @classmethod
    def _no_rotation(cls, data: Any) -> Any:
        # {xyz} alone is {xyz, wpr: [0, 0, 0]}: one value, one model (and one written form)
        if isinstance(data, dict) and "xyz" in data and data.keys().isdisjoint(
            ("wpr", "matrix", "convention", "values")
        ):
            return {**data, "wpr": (0.0, 0.0, 0.0)}
        return data

    @model_validator(mode="after")
    def _one_form(self) -> Pose:
        given = [k for k, v in (("xyz", self.xyz), ("wpr", self.wpr), ("matrix", self.rows),
                                ("convention", self.convention), ("values", self.values))
                 if v is not None]
        forms = {("xyz", "wpr"), ("matrix",), ("convention", "values")}
        if tuple(given) not in forms:
            raise ValueError(
                "a pose is {xyz, wpr} (FANUC, mm and deg), {matrix} (4x4 rows, mm) or "
                f"{{convention, values}}; got {given or 'no pose keys'}"
            )
        if self.xyz is not None:
            if not np.all(np.isfinite([*self.xyz, *(self.wpr or ())])):
                raise ValueError(
                    f"xyz/wpr must be finite, got xyz {list(self.xyz)} wpr {list(self.wpr or ())}"
                )
        elif self.rows is not None:
            try:
                _rows_matrix(self.rows)
            except ValueError as err:
                raise ValueError(f"{err} (matrix: {[list(r) for r in self.rows]})") from None
        else:
            assert self.convention is not None and self.values is not None
            try:
                _robot_matrix(self.convention, self.values)
            except ValueError as err:
                raise ValueError(f"{err} (values: {list(self.values)})") from None
        return self

    @model_serializer(mode="plain")
    def _written_form(self) -> dict[str, Any]:
        if self.xyz is not None:
            return {"xyz": list(self.xyz), "wpr": list(self.wpr or ())}
        if self.rows is not None:
            return {"matrix": [list(r) for r in self.rows]}
        assert self.convention is not None and self.values is not None
        return {"convention": self.convention.value, "values": list(self.values)}

    @property
    def matrix(self) -> Array:
        """The 4x4 transform (read-only: copy it to change it)."""
        if self.xyz is not None:
            return _pose_matrix(self.xyz, self.wpr or (0.0, 0.0, 0.0))
        if self.rows is not None:
            return _rows_matrix(self.rows)
        assert self.convention is not None and self.values is not None
        return _robot_matrix(self.convention, self.values)

    @classmethod
    def from_matrix(
        cls, T: Array, form: Literal["wpr", "matrix"] | RobotConvention = "wpr"
    ) -> Pose:
        """A pose of ``T`` written as FANUC ``{xyz, wpr}`` (default), as a ``matrix`` (exact),
        or in a robot convention."""
        T = np.asarray(T, dtype=float)
        if form == "matrix":
            rows = tuple(tuple(float(x) for x in r) for r in T)
            return cls.model_validate({"matrix": rows})
        if form != "wpr":
            conv = RobotConvention(form)
            return cls(convention=conv, values=tuple(float(x) for x in to_robot(T, conv)))
        v = matrix_to_xyzwpr(T)
        return cls(
            xyz=(float(v[0]), float(v[1]), float(v[2])), wpr=(float(v[3]), float(v[4]), float(v[5]))
        )


# ------------------------------------------------------------------------------- cameras


class SimFault(_Model):
    """A fault the simulated camera injects (for tests and demos)."""

    kind: Literal["none", "timeout", "disconnect", "corrupt"] = "none"
    every_n: int = Field(0, ge=0, description="inject on every n-th grab (0 = never)")
    down_ms: float = Field(
        0.0, ge=0, description="disconnect: how long the camera cannot be reopened"
    )


class DriverConfig(_Model):
    """Which backend drives a camera and how it is opened and configured."""

    kind: Literal["sim", "genicam", "pylon", "files"]
    serial: str | None = None
    user_id: str | None = None
    cti: str | None = Field(None, description="GenTL producer (.cti) path, genicam only")
    folder: str | None = Field(None, description="image folder, files only")
    exposure_us: float = Field(5000.0, gt=0)
    gain_db: float = Field(0.0, ge=0)
    trigger: Literal["software", "hardware", "free_run"] = "software"
    grab_timeout_ms: float = Field(200.0, gt=0)
    latency_ms: float = Field(0.0, ge=0, description="sim only: delay before a frame is ready")
    image_noise: float = Field(2.0, ge=0, description="sim only: read noise, grey levels")
    fault: SimFault = SimFault()
    features: dict[str, str | int | float | bool] = Field(
        default_factory=dict,
        description="GenICam features set after configure (genicam, pylon), in order; "
        "e.g. pylon emulation's ImageFilename, ImageFileMode, TestImageSelector",
    )

    @model_validator(mode="after")
    def _check_kind(self) -> DriverConfig:
        if self.kind in ("genicam", "pylon") and not (self.serial or self.user_id):
            raise ValueError(f"a {self.kind} camera needs 'serial' or 'user_id'")
        if self.kind == "files" and not self.folder:
            raise ValueError("a files camera needs 'folder'")
        return self


class Intrinsics(_Model):
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


class CameraConfig(_Model):
    """One physical camera."""

    id: Identifier
    driver: DriverConfig
    image_size: tuple[int, int] = Field(description="width, height in px")
    pixel_format: Literal["mono8", "mono10", "mono12", "mono16"] = "mono8"
    intrinsics: Intrinsics
    distortion: list[float] = Field(
        default_factory=lambda: [0.0] * 5, description="OpenCV k1 k2 p1 p2 [k3 [k4 k5 k6]]"
    )

    @model_validator(mode="after")
    def _check(self) -> CameraConfig:
        if len(self.distortion) not in (4, 5, 8):
            raise ValueError(f"distortion needs 4, 5 or 8 coefficients, got {len(self.distortion)}")
        if self.image_size[0] <= 0 or self.image_size[1] <= 0:
            raise ValueError(f"image_size must be positive, got {list(self.image_size)}")
        return self

    @property
    def model(self) -> CameraModel:
        i = self.intrinsics
        return CameraModel(
            fx=i.fx,
            fy=i.fy,
            cx=i.cx,
            cy=i.cy,
            width=self.image_size[0],
            height=self.image_size[1],
            dist=tuple(self.distortion),
        )


# ------------------------------------------------------------------------------- rigs, views


class RigCamera(_Model):
    camera: Identifier
    T_rig_from_cf: Pose = Pose(xyz=(0.0, 0.0, 0.0))


class RigConfig(_Model):
    """Cameras held rigidly together: on the robot flange, or fixed in the cell."""

    id: Identifier
    mount: Literal["robot", "fixed"]
    cameras: list[RigCamera] = Field(min_length=1)
    T_gf_from_rig: Pose | None = Field(None, description="hand-eye: rig in flange frame (robot)")
    T_rf_from_rig: Pose | None = Field(None, description="rig in robot base frame (fixed)")

    @model_validator(mode="after")
    def _check(self) -> RigConfig:
        if self.mount == "robot" and (self.T_gf_from_rig is None or self.T_rf_from_rig is not None):
            raise ValueError(
                "a robot-mounted rig needs T_gf_from_rig (hand-eye) and no T_rf_from_rig"
            )
        if self.mount == "fixed" and (self.T_rf_from_rig is None or self.T_gf_from_rig is not None):
            raise ValueError("a fixed rig needs T_rf_from_rig and no T_gf_from_rig")
        ids = [c.camera for c in self.cameras]
        if len(set(ids)) != len(ids):
            raise ValueError(f"rig lists a camera twice: {ids}")
        return self


class ViewConfig(_Model):
    """Where the station looks from: a robot flange pose (robot rigs) or the fixed rigs."""

    id: int = Field(ge=1, le=255, description="1-based view index, as the PLC sends it")
    rigs: list[Identifier] = Field(min_length=1)
    T_rf_from_gf: Pose | None = Field(None, description="taught flange pose for robot rigs")


# ------------------------------------------------------------------------------- recipes


Polarity = Literal["dark_on_light", "light_on_dark"]


class MarkConfig(_Model):
    id: Identifier
    position: Vec3 = Field(description="mark centre in the part frame PF, mm (from CAD)")
    normal: Vec3 = Field((0.0, 0.0, 1.0), description="outward surface normal in PF")
    diameter_mm: float | None = Field(
        None, gt=0, description="this mark's diameter; default the recipe's mark_diameter_mm"
    )
    polarity: Polarity | None = Field(None, description="this mark's; default the recipe's")

    @model_validator(mode="after")
    def _check(self) -> MarkConfig:
        if not np.all(np.isfinite(self.position)):
            raise ValueError(f"mark position must be finite, got {list(self.position)}")
        n = float(np.linalg.norm(self.normal))
        if not np.isfinite(n) or n < 1e-9:
            raise ValueError(f"mark normal must be a non-zero vector, got {list(self.normal)}")
        return self


class Sighting(_Model):
    """Marks a camera is expected to see in a view."""

    view: int = Field(ge=1)
    camera: Identifier
    marks: list[Identifier] = Field(min_length=1)


class Tolerances(_Model):
    """Quality gate of a recipe (the paper's grasp needs 0.2° and 1.0 mm)."""

    rotation_deg: float = Field(0.2, gt=0, description="max 1σ rotation at the grasp point")
    translation_mm: float = Field(1.0, gt=0, description="max 1σ translation at the grasp point")
    max_rms_px: float = Field(1.0, gt=0, description="max RMS reprojection error")
    max_residual_px: float = Field(3.0, gt=0, description="max single reprojection residual")
    min_marks: int | None = Field(None, ge=3, description="marks needed; default all")
    max_offset_mm: float = Field(100.0, gt=0, description="displacement the station accepts")
    max_offset_deg: float = Field(10.0, gt=0, description="rotation the station accepts")


class RobustConfig(_Model):
    """How the estimator treats observations inconsistent with the rest (docs/engine.md)."""

    outlier_px: float | None = Field(
        0.5, gt=0, description="an observation whose residual exceeds this is replaced by its "
        "next candidate or dropped; null: every observation is kept"
    )
    candidates: bool = Field(True, description="try a mark's next candidates before dropping it")
    max_dropped: int = Field(4, ge=0, description="observations the rule may drop per trigger")
    loss: Literal["linear", "huber"] = "linear"
    huber_px: float = Field(2.0, gt=0, description="Huber loss threshold, px")
    stereo_check: bool = Field(True, description="epipolar check between cameras of one view")
    epipolar_px: float = Field(2.0, gt=0, description="stereo check: largest epipolar distance")


class RecipeConfig(_Model):
    """A part type and how the station measures it."""

    name: Identifier
    version: int = Field(1, ge=1)
    description: str = ""
    marks: list[MarkConfig] = Field(min_length=3)
    mark_diameter_mm: float = Field(gt=0)
    polarity: Polarity = "dark_on_light"
    sightings: list[Sighting] = Field(min_length=1)
    T_rf_from_pf0: Pose = Field(description="part pose at the taught reference (zero offset)")
    T_pf_from_grasp: Pose = Field(
        Pose(xyz=(0.0, 0.0, 0.0)), description="grasp (tool) frame in the part frame"
    )
    robot_convention: RobotConvention = RobotConvention.FANUC
    detector_noise_px: float = Field(0.1, gt=0, description="a-priori σ of a mark centre")
    tolerances: Tolerances = Tolerances()
    robust: RobustConfig = RobustConfig()
    nok_streak_warning: int = Field(
        3, ge=1, le=1000, description="the line view warns after this many NOKs in a row")

    @model_validator(mode="after")
    def _check(self) -> RecipeConfig:
        ids = [m.id for m in self.marks]
        if len(set(ids)) != len(ids):
            raise ValueError(f"mark ids must be unique, got {ids}")
        known = set(ids)
        for s in self.sightings:
            unknown = [m for m in s.marks if m not in known]
            if unknown:
                raise ValueError(
                    f"sighting view {s.view} camera {s.camera!r} names unknown marks {unknown}"
                )
        tm = self.tolerances.min_marks
        if tm is not None and tm > len(ids):
            raise ValueError(f"tolerances.min_marks = {tm} exceeds the {len(ids)} marks")
        return self

    @property
    def min_marks(self) -> int:
        return self.tolerances.min_marks or len(self.marks)

    def mark_positions(self) -> Array:
        """Mark centres ``["M", 3]`` in PF, in the order of :attr:`marks`."""
        return np.array([m.position for m in self.marks], dtype=float)

    def mark_diameters(self) -> Array:
        """Each mark's diameter ``["M"]`` (mm; the recipe's unless the mark has its own)."""
        return np.array(
            [self.mark_diameter_mm if m.diameter_mm is None else m.diameter_mm
             for m in self.marks], dtype=float,
        )

    def mark_dark(self) -> Array:
        """``["M"]`` bool: which marks are dark on a light surface."""
        return np.array(
            [(m.polarity or self.polarity) == "dark_on_light" for m in self.marks], dtype=bool
        )

    def mark_centroid(self) -> Array:
        """The marks' centroid in PF (mm): the centre of the part's allowed rotation."""
        return self.mark_positions().mean(axis=0)

    def mark_index(self, mark_id: str) -> int:
        for i, m in enumerate(self.marks):
            if m.id == mark_id:
                return i
        raise KeyError(f"recipe {self.name!r} has no mark {mark_id!r}")


# ------------------------------------------------------------------------------- station

#: the operator page's languages (server/web/locale holds a catalogue for each but English,
#: the source); zh_Hans is Simplified Chinese
PAGE_LANGUAGES = ("en", "de", "zh_Hans", "es")

#: the operator page logs out after this long without a user action (s): a quarter of an hour
#: keeps a panel PC logged in through a part change or a short talk at the line, and a login
#: left behind at a break does not outlast it
IDLE_LOGOUT_S = 900.0


class DriftConfig(_Model):
    """The drift watch's settings (docs/calibration.md, "Drift watch")."""

    history: int = Field(
        DriftOptions.history, ge=100, le=1_000_000,
        description="triggers per camera the watch keeps to date a drift and estimate its move "
                    "(32 bytes a camera and 16 a trigger with the server's record ids: 2.7 MiB for "
                    "4 cameras at 20,000); a "
                    "drift that began earlier is measured over the kept ones only")


class PageConfig(_Model):
    """The operator page on this station's panel PCs."""

    idle_logout_s: float = Field(
        IDLE_LOGOUT_S, ge=1, le=86400,
        description="a page session ends this long after its user's last action (a click, a "
                    "key, a page opened); background refreshes do not count")
    kiosk: bool = Field(
        False, description="the line view (/line) and its NOK thumbnails are readable without "
                           "a login, read-only (a panel PC beside the line); every other page "
                           "still needs a login")
    language: Literal["en", "de", "zh_Hans", "es"] | None = Field(
        None, description="the page's language unless a user picks one: en, de, zh_Hans "
                          "(Simplified Chinese) or es; unset: the browser's Accept-Language")


class StationConfig(_Model):
    """The whole station."""

    name: Identifier
    description: str = ""
    deadline_ms: float = Field(50.0, gt=0, description="trigger → result budget")
    cameras: list[CameraConfig] = Field(min_length=1)
    rigs: list[RigConfig] = Field(min_length=1)
    views: list[ViewConfig] = Field(min_length=1)
    recipes: list[RecipeConfig] = Field(min_length=1)
    default_recipe: Identifier | None = None
    calibration: str | None = Field(None, description="calibration file this station uses")
    calibration_board: str | None = Field(
        None, description="the calibration board a robot-driven hand-eye session looks at, as "
        "mvpose calibrate's --board writes it (e.g. charuco:15x11:40:30); docs/calibration.md")
    links: dict[str, Any] = Field(
        default_factory=dict,
        description="PLC and controller links: backend name → its settings, each block checked by "
                    "its backend's own model where the server loads the file "
                    "(drivers.links.link_settings)")
    plant: PlantConfig | None = Field(
        None, description="ISA-95 names and the MQTT broker results stream to")
    uncertainty: UncertaintyConfig = Field(
        UncertaintyConfig(), description="detector noise pooling and calibration 1σ"
    )
    shifts: list[Shift] = Field(list(DEFAULT_SHIFTS), description="shift starts (line view)")
    time_zone: str = Field("UTC", description="the plant's IANA time zone (shift starts, the "
                                              "operator page's times)")
    page: PageConfig = Field(PageConfig(), description="the operator page: idle logout, kiosk, "
                                                       "the plant's language")
    drift: DriftConfig = Field(DriftConfig(), description="the drift watch's history")
    calibration_max_age_days: float | None = Field(
        None, gt=0, le=3650, description="an alarm when the active calibration is older "
        "(docs/alarms.md); none: no limit")

    @model_validator(mode="after")
    def _check_shifts(self) -> StationConfig:
        check_shifts(self.shifts)
        time_zone(self.time_zone)
        return self

    @model_validator(mode="after")
    def _cross_check(self) -> StationConfig:
        cams = _unique([c.id for c in self.cameras], "camera")
        rigs = {r.id: r for r in self.rigs}
        _unique(list(rigs), "rig")
        seen: dict[str, str] = {}
        for r in self.rigs:
            for rc in r.cameras:
                if rc.camera not in cams:
                    raise ValueError(f"rig {r.id!r} names unknown camera {rc.camera!r}")
                if rc.camera in seen:
                    raise ValueError(
                        f"camera {rc.camera!r} is in rigs {seen[rc.camera]!r} and {r.id!r}"
                    )
                seen[rc.camera] = r.id
        _unique([str(v.id) for v in self.views], "view")
        for v in self.views:
            mounts = set()
            for rid in v.rigs:
                if rid not in rigs:
                    raise ValueError(f"view {v.id} names unknown rig {rid!r}")
                mounts.add(rigs[rid].mount)
            if "robot" in mounts and v.T_rf_from_gf is None:
                raise ValueError(f"view {v.id} holds a robot-mounted rig and needs T_rf_from_gf")
            if mounts == {"fixed"} and v.T_rf_from_gf is not None:
                raise ValueError(f"view {v.id} holds only fixed rigs and must not set T_rf_from_gf")
        _unique([r.name for r in self.recipes], "recipe")
        for rec in self.recipes:
            for s in rec.sightings:
                view = self.view(s.view) if s.view in {v.id for v in self.views} else None
                if view is None:
                    raise ValueError(f"recipe {rec.name!r}: sighting names unknown view {s.view}")
                if s.camera not in cams:
                    raise ValueError(
                        f"recipe {rec.name!r}: sighting names unknown camera {s.camera!r}"
                    )
                if seen.get(s.camera) not in view.rigs:
                    raise ValueError(
                        f"recipe {rec.name!r}: camera {s.camera!r} is not in view {s.view}"
                    )
        if self.default_recipe is not None and self.default_recipe not in {
            r.name for r in self.recipes
        }:
            raise ValueError(f"default_recipe {self.default_recipe!r} is not a recipe")
        return self

    @field_validator("calibration_board")
    @classmethod
    def _check_board(cls, value: str | None) -> str | None:
        if value is not None:
            from mvpose_core.calibration.boards import BoardSpec

            BoardSpec.parse(value)  # its ValueError names what is wrong with the text
        return value

    @model_validator(mode="after")
    def _check_uncertainty(self) -> StationConfig:
        u = self.uncertainty
        for what, given, known in (("rigs", u.rigs, {r.id for r in self.rigs}),
                                   ("cameras", u.cameras, {c.id for c in self.cameras})):
            unknown = sorted(set(given) - known)
            if unknown:
                raise ValueError(f"uncertainty.{what} names unknown {what[:-1]}s {unknown}")
        return self

    # -------------------------------------------------------------- look-ups
    def camera(self, camera_id: str) -> CameraConfig:
        for c in self.cameras:
            if c.id == camera_id:
                return c
        raise KeyError(f"station {self.name!r} has no camera {camera_id!r}")

    def rig(self, rig_id: str) -> RigConfig:
        for r in self.rigs:
            if r.id == rig_id:
                return r
        raise KeyError(f"station {self.name!r} has no rig {rig_id!r}")

    def view(self, view_id: int) -> ViewConfig:
        for v in self.views:
            if v.id == view_id:
                return v
        raise KeyError(f"station {self.name!r} has no view {view_id}")

    def recipe(self, name: str | None = None) -> RecipeConfig:
        name = name or self.default_recipe or self.recipes[0].name
        for r in self.recipes:
            if r.name == name:
                return r
        raise KeyError(f"station {self.name!r} has no recipe {name!r}")

    def rig_of(self, camera_id: str) -> RigConfig:
        for r in self.rigs:
            if any(rc.camera == camera_id for rc in r.cameras):
                return r
        raise KeyError(f"camera {camera_id!r} is in no rig")

    def view_camera_ids(self, view_id: int) -> list[str]:
        """Cameras that take a picture in a view, in rig order."""
        return [rc.camera for rid in self.view(view_id).rigs for rc in self.rig(rid).cameras]

    @property
    def robot_mounted(self) -> bool:
        return any(r.mount == "robot" for r in self.rigs)

    def iter_view_cameras(self) -> Iterator[tuple[int, str]]:
        for v in self.views:
            for cid in self.view_camera_ids(v.id):
                yield v.id, cid


def _unique(ids: list[str], what: str) -> set[str]:
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"{what} ids must be unique, repeated: {dup}")
    return set(ids)


# ------------------------------------------------------------------------------- loading


def _format_loc(loc: tuple[Any, ...], data: Any) -> str:
    """Turn a pydantic location into a readable path, with ids instead of list indices."""
    parts: list[str] = []
    node = data
    for item in loc:
        if isinstance(item, int) and isinstance(node, list) and 0 <= item < len(node):
            node = node[item]
            label = node.get("id", node.get("name")) if isinstance(node, dict) else None
            parts.append(f"[{item}]" + (f"({label})" if label is not None else ""))
        else:
            node = node.get(item) if isinstance(node, dict) else None
            parts.append(("." if parts else "") + str(item))
    return "".join(parts) or "<top level>"


def parse_station(data: Any, source: str = "<memory>") -> StationConfig:
    """Validate a station description; errors name the source, the field and the value."""
    if not isinstance(data, dict):
        raise StationFileError(
            f"{source}: expected a mapping at the top level, got {type(data).__name__}"
        )
    try:
        return StationConfig.model_validate(data)
    except ValidationError as err:
        lines = [problem_line(source, _format_loc(tuple(e["loc"]), data), e["msg"],
                              e.get("input")) for e in err.errors()]
        raise StationFileError("\n".join(lines)) from None


def problem_line(source: str, where: str, message: str, value: Any) -> str:
    """One problem of a station file as StationFileError names it: file, field, what, value."""
    shown = repr(value) if not isinstance(value, dict) else "{…}"
    if len(shown) > 80:
        shown = shown[:77] + "..."
    return f"{source}: {where}: {message} (value: {shown})"


def load_station(path: str | Path) -> StationConfig:
    """Read and validate a station YAML file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise StationFileError(f"{path}: cannot read station file: {err.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise StationFileError(f"{path}: not valid YAML: {err}") from None
    return parse_station(data, str(path))


def dump_station(station: StationConfig) -> str:
    """YAML text of a station (round-trips through :func:`parse_station`)."""
    return yaml.safe_dump(station.model_dump(mode="json", exclude_defaults=False), sort_keys=False)
