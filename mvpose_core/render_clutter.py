"""Clutter and occluders for the renderer: panel edges, holes that are not marks, specular spots.

Everything is painted into the albedo image (before blur and noise) with anti-aliased edges from
signed distances, only over each object's bounding box. Clutter is placed near the marks, where a
detector's windows look, but never overlapping a mark: a detector must reject it, not be spared it.
"""

from __future__ import annotations

import numpy as np

from mvpose_core.transforms import Array

Footprint = tuple[Array, float]  # (centre uv, radius px) of a drawn mark


def _blend(
    albedo: np.ndarray, box: tuple[int, int, int, int], cover: np.ndarray, value: float
) -> None:
    u0, v0, u1, v1 = box
    patch = albedo[v0:v1, u0:u1]
    c = cover.astype(np.float32)
    patch[:] = patch * (1.0 - c) + np.float32(value) * c


def _box(albedo: np.ndarray, uv: Array, half: float) -> tuple[int, int, int, int] | None:
    H, W = albedo.shape
    u0, v0 = int(np.floor(uv[0] - half)), int(np.floor(uv[1] - half))
    u1, v1 = int(np.ceil(uv[0] + half)) + 1, int(np.ceil(uv[1] + half)) + 1
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, W), min(v1, H)
    return (u0, v0, u1, v1) if u1 > u0 and v1 > v0 else None


def _grid(box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    u0, v0, u1, v1 = box
    vv, uu = np.mgrid[v0:v1, u0:u1]
    return uu.astype(float), vv.astype(float)


def paint_ellipse(
    albedo: np.ndarray, uv: Array, a: float, b: float, angle_rad: float, value: float
) -> None:
    """An anti-aliased filled ellipse (semi-axes ``a``, ``b`` px) of albedo ``value``."""
    box = _box(albedo, uv, max(a, b) + 2.0)
    if box is None:
        return
    uu, vv = _grid(box)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x = c * (uu - uv[0]) + s * (vv - uv[1])
    y = -s * (uu - uv[0]) + c * (vv - uv[1])
    q = np.sqrt((x / a) ** 2 + (y / b) ** 2) + 1e-12
    grad = np.sqrt((x / a**2) ** 2 + (y / b**2) ** 2) / q + 1e-12
    _blend(albedo, box, np.clip(0.5 - (q - 1.0) / grad, 0.0, 1.0), value)


def paint_spot(albedo: np.ndarray, uv: Array, sigma: float, peak: float) -> None:
    """A specular highlight: a Gaussian bump adding ``peak`` albedo at its centre."""
    box = _box(albedo, uv, 4.0 * sigma)
    if box is None:
        return
    uu, vv = _grid(box)
    bump = peak * np.exp(-((uu - uv[0]) ** 2 + (vv - uv[1]) ** 2) / (2.0 * sigma**2))
    u0, v0, u1, v1 = box
    albedo[v0:v1, u0:u1] += bump.astype(np.float32)


def _chord_offset(fraction: float) -> float:
    """Distance (in radii) from a disc's centre of the chord that cuts off ``fraction`` of it."""
    s = np.linspace(-1.0, 1.0, 401)
    cut = (np.arccos(s) - s * np.sqrt(1.0 - s * s)) / np.pi  # area beyond the chord, decreasing
    return float(np.interp(fraction, cut[::-1], s[::-1]))


def paint_occluder(
    albedo: np.ndarray, uv: Array, r: float, bg_albedo: float, rng: np.random.Generator,
    fraction: tuple[float, float] = (0.4, 0.6),
) -> None:
    """Hide a share in ``fraction`` (default 40–60 %) of the mark at ``uv`` (radius ``r`` px)
    under a bar (a clamp, a cable)."""
    box = _box(albedo, uv, 3.0 * r + 2.0)
    if box is None:
        return
    uu, vv = _grid(box)
    ang = rng.uniform(0.0, 2.0 * np.pi)
    d = np.array([np.cos(ang), np.sin(ang)])
    # the bar's near edge, from the mark centre
    start = _chord_offset(float(rng.uniform(*fraction))) * r
    along = (uu - uv[0]) * d[0] + (vv - uv[1]) * d[1]
    across = -(uu - uv[0]) * d[1] + (vv - uv[1]) * d[0]
    # Signed distance to the bar [start, start + 2.5 r] x [-2.5 r, 2.5 r] (max of the half-planes).
    sd = np.maximum.reduce([start - along, along - (start + 2.5 * r), np.abs(across) - 2.5 * r])
    value = bg_albedo * rng.choice([1.15, 0.75])
    _blend(albedo, box, np.clip(0.5 - sd, 0.0, 1.0), float(value))


def paint_decoy(
    albedo: np.ndarray, uv: Array, r: float, mark_albedo: float, rng: np.random.Generator,
    gap: tuple[float, float] = (1.0, 2.5),
) -> Array:
    """A dot of the mark's own size and albedo next to the mark at ``uv`` (radius ``r`` px), its
    rim ``gap`` radii from the mark's rim, in a random direction; returns its centre."""
    ang = rng.uniform(0.0, 2.0 * np.pi)
    at = uv + (2.0 * r + rng.uniform(*gap) * r) * np.array([np.cos(ang), np.sin(ang)])
    paint_ellipse(albedo, at, r, r, 0.0, mark_albedo)
    return at


def _clear_of(uv: Array, extent: float, footprints: list[Footprint], gap: float) -> bool:
    return all(np.hypot(*(uv - c)) > r + extent + gap for c, r in footprints)


def paint_clutter(
    albedo: np.ndarray,
    footprints: list[Footprint],
    bg_albedo: float,
    mark_albedo: float,
    rng: np.random.Generator,
) -> None:
    """Panel edges, holes of other sizes and shapes, and specular spots, near and between marks."""
    H, W = albedo.shape
    r_ref = float(np.median([r for _, r in footprints])) if footprints else 15.0

    # Panel edges: a step in albedo along a straight line that passes close to (not over) marks.
    for k in range(2):
        for _ in range(50):
            if footprints and k == 0:
                c, r = footprints[rng.integers(len(footprints))]
                ang = rng.uniform(0.0, np.pi)
                n = np.array([np.cos(ang), np.sin(ang)])
                offset = float(n @ c) + rng.choice([-1.0, 1.0]) * rng.uniform(r + 8.0, r + 40.0)
            else:
                ang = rng.uniform(0.0, np.pi)
                n = np.array([np.cos(ang), np.sin(ang)])
                offset = float(n @ rng.uniform([0.0, 0.0], [W, H]))
            if all(abs(float(n @ c) - offset) > r + 6.0 for c, r in footprints):
                break
        else:
            continue
        uu = np.arange(W, dtype=np.float32)[None, :]
        vv = np.arange(H, dtype=np.float32)[:, None]
        sd = np.float32(n[0]) * uu + np.float32(n[1]) * vv - np.float32(offset)
        cover = np.clip(np.float32(0.5) - sd, 0.0, 1.0)
        albedo *= 1.0 - np.float32(0.25) * cover  # the far side is a darker panel

    # Holes and slots that are not marks, and specular spots: near each mark and anywhere.
    anchors = [(c, r) for c, r in footprints for _ in range(3)]
    anchors += [(rng.uniform([0.0, 0.0], [W, H]), 0.0) for _ in range(12)]
    for k, (c, r) in enumerate(anchors):
        kind = k % 4
        if kind == 0:
            a = b = 0.5 * r_ref  # a small hole
        elif kind == 1:
            a = b = 2.0 * r_ref  # a large hole
        elif kind == 2:
            a, b = 1.6 * r_ref, 0.45 * r_ref  # a slot
        else:
            a = b = 4.0 * rng.uniform(1.0, 2.5)  # a specular spot's extent (4 sigma)
        for _ in range(30):
            ang = rng.uniform(0.0, 2.0 * np.pi)
            dist = r + a + rng.uniform(4.0, 2.0 * r_ref + 10.0) if r > 0 else 0.0
            uv = c + dist * np.array([np.cos(ang), np.sin(ang)])
            if 0 <= uv[0] < W and 0 <= uv[1] < H and _clear_of(uv, max(a, b), footprints, 4.0):
                break
        else:
            continue
        if kind == 3:
            paint_spot(albedo, uv, a / 4.0, 4.0 * bg_albedo)
        else:
            paint_ellipse(albedo, uv, a, b, rng.uniform(0.0, np.pi), mark_albedo)
