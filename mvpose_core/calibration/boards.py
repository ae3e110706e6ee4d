"""Calibration boards: definitions, OpenCV detection, and a renderer for images with known truth.

Board frame BF: x along the columns, y along the rows, z = x × y pointing into the board (away from
a camera that sees its printed face), origin where OpenCV puts it for that board kind:

- ``chessboard``: the first inner corner; corner ``k`` is at ``((k % cols)·s, (k // cols)·s, 0)``.
- ``charuco``: the outer corner of the board; OpenCV's ``CharucoBoard.getChessboardCorners()``.
- ``circles`` (asymmetric grid): the first circle; circle ``k`` in row ``j = k // cols`` is at
  ``((2·(k % cols) + j % 2)·s, j·s, 0)``.

A :class:`Detection` keeps the corner ids next to their pixels, so a partly seen ChArUco board is
matched to the model by id, never by position in a list.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, invert

BoardKind = Literal["chessboard", "charuco", "circles"]

_BLACK = 25.0
_WHITE = 225.0
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board. ``cols`` × ``rows`` count inner corners (chessboard), squares (charuco)
    or circles per row × rows (circles); ``square_mm`` is the square size or the circle spacing."""

    kind: BoardKind
    cols: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0  # charuco marker side, circles diameter
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco", "circles"):
            raise ValueError(
                f"board kind must be chessboard, charuco or circles, got {self.kind!r}"
            )
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"{self.kind} board needs at least 2x2, got {self.cols}x{self.rows}")
        if not (np.isfinite(self.square_mm) and self.square_mm > 0):
            raise ValueError(f"board square_mm must be positive, got {self.square_mm}")
        if self.kind == "chessboard" and (self.cols + self.rows) % 2 == 0:
            # With an even sum the pattern is symmetric under a 180° turn and the detector cannot
            # tell corner 0 from the last corner: every pose could be off by 180°.
            raise ValueError(
                f"chessboard {self.cols}x{self.rows} inner corners is 180°-symmetric; "
                "use one odd and one even count (e.g. 9x6)"
            )
        if self.kind in ("charuco", "circles") and not (0 < self.marker_mm < self.square_mm):
            raise ValueError(
                f"{self.kind} board needs 0 < marker_mm < square_mm, got {self.marker_mm} "
                f"and {self.square_mm}"
            )
        if self.kind == "charuco" and not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    # ------------------------------------------------------------------ text form
    @classmethod
    def parse(cls, text: str) -> BoardSpec:
        """Parse ``chessboard:9x6:25``, ``charuco:7x5:30:22:DICT_5X5_100`` or circles:4x11:20:10."""
        m = re.fullmatch(
            r"(chessboard|charuco|circles):(\d+)x(\d+):([0-9.]+)(?::([0-9.]+))?(?::(DICT_\w+))?",
            text.strip(),
        )
        if not m:
            raise ValueError(
                f"board {text!r} not understood; expected e.g. chessboard:9x6:25, "
                "charuco:7x5:30:22:DICT_5X5_100 or circles:4x11:20:10"
            )
        kind, cols, rows, sq, marker, dictionary = m.groups()
        return cls(
            kind=kind,  # type: ignore[arg-type]
            cols=int(cols),
            rows=int(rows),
            square_mm=float(sq),
            marker_mm=float(marker or 0.0),
            dictionary=dictionary or "DICT_5X5_100",
        )

    def __str__(self) -> str:
        base = f"{self.kind}:{self.cols}x{self.rows}:{self.square_mm:g}"
        if self.kind == "chessboard":
            return base
        if self.kind == "charuco":
            return f"{base}:{self.marker_mm:g}:{self.dictionary}"
        return f"{base}:{self.marker_mm:g}"

    # ------------------------------------------------------------------ geometry
    @cached_property
    def object_points(self) -> Array:
        """Every corner (circle centre) in BF, mm, ``["N", 3]``; row ``k`` is corner id ``k``."""
        s = self.square_mm
        if self.kind == "charuco":
            return np.asarray(self._charuco.getChessboardCorners(), dtype=float).reshape(-1, 3)
        k = np.arange(self.cols * self.rows)
        i, j = k % self.cols, k // self.cols
        x = i * s if self.kind == "chessboard" else (2 * i + j % 2) * s
        return np.stack([x, j * s, np.zeros_like(k, dtype=float)], axis=1).astype(float)

    @property
    def n_corners(self) -> int:
        return int(self.object_points.shape[0])

    @cached_property
    def _charuco(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm, d)

    def extent_mm(self) -> tuple[float, float, float, float]:
        """Printed area ``(x0, y0, x1, y1)`` in BF, including the white quiet zone."""
        s = self.square_mm
        if self.kind == "chessboard":
            return (-2 * s, -2 * s, (self.cols + 1) * s, (self.rows + 1) * s)
        if self.kind == "charuco":
            return (-s, -s, (self.cols + 1) * s, (self.rows + 1) * s)
        return (-s, -s, (2 * self.cols) * s, self.rows * s)

    def grey_at(self, X: Array, Y: Array) -> Array:
        """Printed grey level at BF points (x, y) in mm; NaN outside the printed area.
        Exact for chessboards and circle grids; ChArUco boards go through :meth:`texture`."""
        x0, y0, x1, y1 = self.extent_mm()
        s = self.square_mm
        on = (x0 <= X) & (x1 >= X) & (y0 <= Y) & (y1 >= Y)
        if self.kind == "chessboard":
            # Square (a, b) spans [(a-1)s, a·s] × [(b-1)s, b·s]; squares 0..cols, 0..rows.
            a = np.floor(X / s) + 1
            b = np.floor(Y / s) + 1
            inside = (a >= 0) & (a <= self.cols) & (b >= 0) & (b <= self.rows)
            black = inside & ((a + b) % 2 == 0)
        elif self.kind == "circles":
            # Circle radius < s/2 < row spacing, so a point can only be in the nearest row's circle.
            j = np.rint(Y / s)
            i = np.rint((X / s - np.mod(j, 2)) / 2)
            cx = (2 * i + np.mod(j, 2)) * s
            d2 = (X - cx) ** 2 + (Y - j * s) ** 2
            ok = (i >= 0) & (i < self.cols) & (j >= 0) & (j < self.rows)
            black = ok & (d2 <= (self.marker_mm / 2) ** 2)
        else:
            raise ValueError("grey_at: ChArUco boards are drawn from their texture")
        return np.where(on, np.where(black, _BLACK, _WHITE), np.nan)

    def texture(self, px_per_mm: float) -> tuple[NDArray[np.float32], float, float]:
        """Board picture (grey levels) and the BF position of pixel (0, 0)'s centre, (x0, y0)."""
        x0, y0, x1, y1 = self.extent_mm()
        w = int(round((x1 - x0) * px_per_mm))
        h = int(round((y1 - y0) * px_per_mm))
        if self.kind == "charuco":
            margin = int(round(self.square_mm * px_per_mm))
            img = self._charuco.generateImage((w, h), marginSize=margin, borderBits=1)
            tex = np.where(img > 127, _WHITE, _BLACK).astype(np.float32)
        else:
            X, Y = np.meshgrid(
                (np.arange(w) + 0.5) / px_per_mm + x0, (np.arange(h) + 0.5) / px_per_mm + y0
            )
            tex = np.nan_to_num(self.grey_at(X, Y), nan=_WHITE).astype(np.float32)
        return tex, x0 + 0.5 / px_per_mm, y0 + 0.5 / px_per_mm


@dataclass(frozen=True)
class Detection:
    """Corners found in one image: ids into :attr:`BoardSpec.object_points` and distorted pixels."""

    ids: NDArray[np.int64]  # ["N"]
    uv: Array  # ["N", 2]

    def __post_init__(self) -> None:
        if self.uv.shape != (self.ids.shape[0], 2):
            raise ValueError(f"detection: {self.ids.shape[0]} ids but uv shape {self.uv.shape}")

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def object_points(self, board: BoardSpec) -> Array:
        return board.object_points[self.ids]


# --------------------------------------------------------------------------- detection


def detect(image: NDArray[np.uint8], board: BoardSpec, min_corners: int = 6) -> Detection | None:
    """Find the board in a mono8 image; None when it is not found (or too few ChArUco corners)."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"detect expects a mono8 image, got {image.dtype} shape {image.shape}")
    if board.kind == "chessboard":
        return _detect_chessboard(image, board)
    if board.kind == "circles":
        found, centers = cv2.findCirclesGrid(
            image, (board.cols, board.rows), flags=cv2.CALIB_CB_ASYMMETRIC_GRID
        )
        if not found:
            return None
        return Detection(np.arange(board.n_corners), centers.reshape(-1, 2).astype(float))
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board._charuco).detectBoard(image)
    if ids is None or len(ids) < min_corners:
        return None
    return Detection(ids.reshape(-1).astype(np.int64), corners.reshape(-1, 2).astype(float))


def _detect_chessboard(image: NDArray[np.uint8], board: BoardSpec) -> Detection | None:
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(image, (board.cols, board.rows), flags=flags)
    if not found:
        return None
    # Window of about a third of the smallest square side seen in the image.
    c = corners.reshape(board.rows, board.cols, 2)
    side = min(
        float(np.min(np.linalg.norm(np.diff(c, axis=1), axis=2))),
        float(np.min(np.linalg.norm(np.diff(c, axis=0), axis=2))),
    )
    win = int(np.clip(side / 3, 2, 15))
    corners = cv2.cornerSubPix(image, corners, (win, win), (-1, -1), _SUBPIX_CRITERIA)
    uv = corners.reshape(-1, 2).astype(float)
    uv = _orient_chessboard(image, board, uv)
    return Detection(np.arange(board.n_corners), uv)


def _orient_chessboard(image: NDArray[np.uint8], board: BoardSpec, uv: Array) -> Array:
    """Reorder corners so that id 0 is the board's first corner (OpenCV may return them reversed
    or mirrored): the square between corners 0, 1, cols, cols+1 is black in BF."""
    grid = uv.reshape(board.rows, board.cols, 2)
    # A proper (non-mirrored) view has the x and y board axes turning clockwise in the image.
    ex = grid[0, 1] - grid[0, 0]
    ey = grid[1, 0] - grid[0, 0]
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:
        grid = grid[:, ::-1]
    centre = grid[:2, :2].reshape(-1, 2).mean(axis=0)
    far = grid[-2:, -2:].reshape(-1, 2).mean(axis=0)
    # Square (1, 1) is black ((a + b) even, see texture) and the square at the far end is white
    # because cols + rows is odd; a 180° turn swaps them.
    if _sample(image, centre) > _sample(image, far):
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2)


def _sample(image: NDArray[np.uint8], uv: Array) -> float:
    x = int(np.clip(round(uv[0]), 1, image.shape[1] - 2))
    y = int(np.clip(round(uv[1]), 1, image.shape[0] - 2))
    return float(image[y - 1 : y + 2, x - 1 : x + 2].mean())


# --------------------------------------------------------------------------- rendering


def render(
    board: BoardSpec,
    camera: CameraModel,
    T_cf_from_bf: Array,
    rng: np.random.Generator,
    noise_grey: float = 2.0,
    supersample: int = 4,
    blur_px: float = 0.6,
) -> NDArray[np.uint8]:
    """Render the board as ``camera`` sees it at ``T_cf_from_bf`` (lens distortion included).

    Every image pixel is traced back to the board plane (undistort, intersect the ray) at
    ``supersample``² points and averaged, then blurred like a real lens and given read noise.
    """
    if camera.width * camera.height > 8_000_000:
        raise ValueError(
            f"render: image {camera.width}x{camera.height} too large for the test renderer"
        )
    # Board coordinates at the pixel corners; the map is smooth, so sub-samples interpolate them
    # bilinearly (exact weights, no fixed-point remap).
    x, y = _corner_rays(camera)
    T_bf_from_cf = invert(T_cf_from_bf)
    R, t = T_bf_from_cf[:3, :3], T_bf_from_cf[:3, 3]
    dz = R[2, 0] * x + R[2, 1] * y + R[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -t[2] / dz
    valid = np.isfinite(lam) & (lam > 0)
    lam = np.where(valid, lam, np.nan)
    X = t[0] + lam * (R[0, 0] * x + R[0, 1] * y + R[0, 2])
    Y = t[1] + lam * (R[1, 0] * x + R[1, 1] * y + R[1, 2])
    if board.kind == "charuco":
        depth = abs(float(T_cf_from_bf[2, 3]))
        x0e, y0e, x1e, y1e = board.extent_mm()
        # About two texture pixels per sub-sample, capped to keep the texture small.
        cap = 4000.0 / max(x1e - x0e, y1e - y0e)
        ppm = float(np.clip(2.0 * supersample * max(camera.fx, camera.fy) / depth, 2.0, cap))
        # Whole texture pixels per square: OpenCV draws the squares in whole pixels, so any
        # other scale prints a board slightly off its declared size (1.6e-4 seen at 235.3).
        ppm = max(round(ppm * board.square_mm), 1) / board.square_mm
        tex, tx0, ty0 = board.texture(ppm)
    background = 0.6 * 0.5 * (_BLACK + _WHITE)
    S = int(supersample)
    acc = np.full((camera.height, camera.width), background * S * S)
    # Supersample only the window where the printed board can be (with a one-pixel margin).
    x0e, y0e, x1e, y1e = board.extent_mm()
    with np.errstate(invalid="ignore"):
        bx, by = X, Y  # lower-case names: ruff reads upper-case ones as constants
        on = (bx >= x0e) & (bx <= x1e) & (by >= y0e) & (by <= y1e)
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    if rows.size == 0:
        r0 = r1 = c0 = c1 = 0
    else:
        r0, r1 = max(rows[0] - 2, 0), min(rows[-1] + 2, camera.height)
        c0, c1 = max(cols[0] - 2, 0), min(cols[-1] + 2, camera.width)
    Xw, Yw = X[r0 : r1 + 1, c0 : c1 + 1], Y[r0 : r1 + 1, c0 : c1 + 1]
    window = np.zeros((r1 - r0, c1 - c0))
    for fy in (np.arange(S) + 0.5) / S:
        for fx in (np.arange(S) + 0.5) / S:
            if window.size == 0:
                break
            Xs = _bilinear(Xw, fx, fy)
            Ys = _bilinear(Yw, fx, fy)
            if board.kind == "charuco":
                g = cv2.remap(
                    tex,
                    ((Xs - tx0) * ppm).astype(np.float32),
                    ((Ys - ty0) * ppm).astype(np.float32),
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=np.nan,
                ).astype(float)
            else:
                g = board.grey_at(Xs, Ys)
            window += np.where(np.isfinite(g), g, background)
    acc[r0:r1, c0:c1] = window
    img = acc / (S * S)
    if blur_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), blur_px), dtype=float)
    img = img + rng.normal(0.0, noise_grey, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@lru_cache(maxsize=8)
def _corner_rays(camera: CameraModel) -> tuple[Array, Array]:
    """Undistorted normalised coordinates of every pixel corner ``["H+1", "W+1"]`` (cached:
    undistorting a whole image grid costs more than the rest of a render)."""
    u, v = np.meshgrid(np.arange(camera.width + 1.0) - 0.5, np.arange(camera.height + 1.0) - 0.5)
    xy = camera.undistort_normalized(np.stack([u.ravel(), v.ravel()], axis=1))
    x, y = xy[:, 0].reshape(u.shape), xy[:, 1].reshape(u.shape)
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def _bilinear(G: Array, fx: float, fy: float) -> Array:
    """Values at fraction (fx, fy) inside every cell of a corner grid ``["H+1", "W+1"]``."""
    return (1 - fy) * ((1 - fx) * G[:-1, :-1] + fx * G[:-1, 1:]) + fy * (
        (1 - fx) * G[1:, :-1] + fx * G[1:, 1:]
    )
