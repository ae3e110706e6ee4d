"""The paper's simulation studies (Section 3.1, Figs 5–8) as data: scenarios, points, stated values.

Hand-eye error levels (1σ per axis, rotation and translation of each view's rig relative to the
first view; see :mod:`mvpose_core.simulation.scenes`). The paper does not give its levels:

* ``zero`` — perfect calibration and robot;
* ``low`` = 0.05° / 0.2 mm — a good hand-eye calibration on a robot that repeats its taught
  poses (an R-2000iA repeats to about ±0.05 mm; hand-eye solutions from 15–20 board poses
  scatter by a few hundredths of a degree and a few tenths of a millimetre);
* ``high`` = 0.2° / 1 mm — an uncompensated robot's absolute positioning between distant poses
  or a careless calibration; the grasping tolerance itself (0.2°, 1 mm), so it shows what an
  error of that size does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from mvpose_core.simulation.scenes import Motion


@dataclass(frozen=True)
class HandEyeLevel:
    """1σ per axis of each view's rig error relative to the first view."""

    name: str
    rot_deg: float
    trans_mm: float


HANDEYE_LEVELS: dict[str, HandEyeLevel] = {
    "zero": HandEyeLevel("zero", 0.0, 0.0),
    "low": HandEyeLevel("low", 0.05, 0.2),
    "high": HandEyeLevel("high", 0.2, 1.0),
}


@dataclass(frozen=True)
class Scenario:
    """How one point's trials are drawn."""

    n_marks: int
    n_views: int
    sigma_px: float
    layout: Literal["cad", "random"] = (
        "random"  # cad = the lab's four marks; random = new per trial
    )
    motion: Motion = "rotate"
    handeye: HandEyeLevel = HANDEYE_LEVELS["zero"]

    def __post_init__(self) -> None:
        if not (self.sigma_px >= 0):
            raise ValueError(f"sigma_px must be ≥ 0, got {self.sigma_px}")
        if self.n_marks < 3:
            raise ValueError(f"a pose needs at least 3 marks, got n_marks={self.n_marks}")
        if self.n_views < 1:
            raise ValueError(f"n_views must be ≥ 1, got {self.n_views}")
        if self.layout == "cad" and self.n_marks != 4:
            raise ValueError(f"the cad layout has 4 marks, got n_marks={self.n_marks}")


@dataclass(frozen=True)
class StudyPoint:
    """One point of a study's curve; ``seed_key`` names its own random stream."""

    study: str
    series: str  # the curve this point belongs to, e.g. a hand-eye level
    x: float
    scenario: Scenario
    seed_key: tuple[int, ...]


@dataclass(frozen=True)
class PaperMark:
    """A value the paper states in its text, to be marked on our plot.

    ``kind``: "point" (a value at x), "ceiling" (below this from x on), "flat_from" (the curve
    stops changing from x on; values unused).
    """

    kind: Literal["point", "ceiling", "flat_from"]
    x: float
    rot_deg: float | None = None
    trans_mm: float | None = None
    label: str = ""


@dataclass(frozen=True)
class Study:
    name: str
    title: str
    x_label: str
    points: tuple[StudyPoint, ...]
    paper: tuple[PaperMark, ...] = field(default_factory=tuple)

    @property
    def series(self) -> list[str]:
        return list(dict.fromkeys(p.series for p in self.points))


#: what the paper reports in the text of Section 3.1 (its figures give no tables)
PAPER_STD = (0.01, 0.1)  # "std of rotation and translation errors about 0.01° and 0.1 mm"

NOISE_PX = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
MARK_COUNTS = (4, 6, 8, 10, 12, 14, 16, 18, 20)
VIEW_COUNTS = (1, 2, 3, 4, 6, 8, 12, 16, 20)
TRANSLATION_NOISE_PX = (0.5, 1.0, 1.5, 2.0)
MOTIONS: tuple[Motion, ...] = ("translate", "rotate")


def _noise() -> Study:
    pts = tuple(
        StudyPoint("noise", "4 marks, 2 views", s, Scenario(4, 2, s, layout="cad"), (1, i))
        for i, s in enumerate(NOISE_PX)
    )
    paper = (PaperMark("point", 1.0, 0.1, 1.0, "paper: ≈0.1°, ≈1 mm at 1 px"),)
    return Study("noise", "Pixel noise (paper Fig. 5)", "detector noise σ [px]", pts, paper)


def _marks() -> Study:
    pts = tuple(
        StudyPoint("marks", "2 views, 1 px", n, Scenario(n, 2, 1.0), (2, i))
        for i, n in enumerate(MARK_COUNTS)
    )
    paper = (PaperMark("flat_from", 16, label="paper: flat beyond ≈16 marks"),)
    return Study("marks", "Number of marks (paper Fig. 6)", "marks", pts, paper)


def _views() -> Study:
    pts = tuple(
        StudyPoint("views", f"hand-eye {lv.name}", n, Scenario(18, n, 1.0, handeye=lv), (3, j, i))
        for j, lv in enumerate(HANDEYE_LEVELS.values())
        for i, n in enumerate(VIEW_COUNTS)
    )
    paper = (
        PaperMark("ceiling", 6, 0.14, 1.8, "paper: < 0.14°, < 1.8 mm from 6 views"),
        PaperMark("flat_from", 6, label="paper: stable from ≈6 views"),
    )
    return Study("views", "Number of views, 18 marks, 1 px (paper Fig. 7)", "views", pts, paper)


def _translation_only() -> Study:
    pts = tuple(
        StudyPoint(
            "translation-only", f"rig {m}s", s, Scenario(4, 2, s, layout="cad", motion=m), (4, j, i)
        )
        for j, m in enumerate(MOTIONS)
        for i, s in enumerate(TRANSLATION_NOISE_PX)
    )
    return Study(
        "translation-only",
        "Rig translating only vs rotating between views (paper Fig. 8)",
        "detector noise σ [px]",
        pts,
    )


STUDIES: dict[str, Study] = {s.name: s for s in (_noise(), _marks(), _views(), _translation_only())}


def get_study(name: str) -> Study:
    """The study called ``name``; ``ValueError`` listing the known ones otherwise."""
    try:
        return STUDIES[name]
    except KeyError:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(STUDIES)}") from None
