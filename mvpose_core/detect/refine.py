"""Measure candidate blobs to sub-pixel accuracy (the candidates themselves: candidates.py).

Rays from the candidate's centre cross the mark's rim; on each ray the edge point is where the
grey profile crosses the middle between the ray's own inner and outer levels (so an
illumination gradient does not pull the edge), and an ellipse is fitted to the edge points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from mvpose_core.detect.ellipse import Ellipse, Ellipses, fit_ellipses

_STEP = 0.5  # px between samples along a ray
_LEVEL_SAMPLES = 3  # samples at each end of a ray that give its inner and outer grey levels
_FINE_RAYS = 96  # most rays of the final edge points (for a radius of 24 px and more)


@dataclass(frozen=True)
class Measurement:
    """A measured mark: fitted ellipse and quality figures, or the reason it failed."""

    ellipse: Ellipse | None
    reason: str | None
    contrast: float
    fit_residual_px: float
    edge_points: int


@lru_cache(maxsize=64)
def _ray_grid(n_rays: int, half: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray angles, their cos and sin ``[1, R, 1]`` and sample offsets ``[S]`` (float32)."""
    phi = np.linspace(0.0, 2.0 * np.pi, n_rays, endpoint=False)
    t = np.arange(-half, half + 1e-9, _STEP).astype(np.float32)
    cos = np.cos(phi).astype(np.float32)[None, :, None]
    sin = np.sin(phi).astype(np.float32)[None, :, None]
    return phi, cos, sin, t


@lru_cache(maxsize=64)
def _mixed_grid(counts: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                  np.ndarray]:
    """Rays for candidates with ray counts of their own, in one array: angles ``[C, R]`` (``R``
    the largest count; candidate ``c`` has the angles of :func:`_ray_grid` for its own count,
    then copies of its first ray), their cos and sin ``[C, R, 1]`` (float32), which rays are
    the candidate's own ``[C, R]``, and the values that stand for the others' contrasts in a
    row median (as many -inf as +inf: every count is a multiple of 16, so the median of a row
    is that of its own rays; float32, as the profiles)."""
    R = max(counts)
    phi = np.zeros((len(counts), R))
    own = np.zeros((len(counts), R), dtype=bool)
    for c, n in enumerate(counts):
        phi[c, :n] = _ray_grid(n, 0.0)[0]
        own[c, :n] = True
    cos = np.cos(phi).astype(np.float32)[:, :, None]
    sin = np.sin(phi).astype(np.float32)[:, :, None]
    pad = np.where(np.cumsum(~own, axis=1) <= (R - own.sum(axis=1))[:, None] // 2, -np.inf,
                   np.inf)
    return phi, cos, sin, own, np.where(own, 0.0, pad).astype(np.float32)


def _rays(
    images: Sequence[np.ndarray],
    owner: np.ndarray,
    ell: Ellipses,
    n_rays: int | np.ndarray,
    half: float,
    dark: bool | np.ndarray,
    lo: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Grey profiles along ``n_rays`` rays per candidate, across its expected rim ± ``half`` px
    (one count for all, or one per candidate ``[C]``: :func:`_mixed_grid`'s rays).

    Candidate ``c`` lies in ``images[owner[c]]``; its own ray is samples ``lo[c]`` to
    ``S - 1 - lo[c]`` (default: all). Returns profiles ``[C, R, S]`` (increasing outwards for
    the recipe's polarity), the radius of every sample, the ray angles ``[R]`` (or ``[C, R]``)
    and which rays lie wholly inside their image ``[C, R]`` (a candidate's own rays only).
    Sampling is OpenCV's bilinear ``remap`` (1/32 px positions, 8-bit values): both
    quantisations are far below the noise and average out over the rim.
    """
    own: np.ndarray | None = None
    if isinstance(n_rays, int):
        phi, cos, sin, t = _ray_grid(n_rays, half)
    else:
        phi, cos, sin, own, _ = _mixed_grid(tuple(n_rays.tolist()))
        t = _ray_grid(int(n_rays.max()), half)[3]
    radii = ell.radius_towards(phi).astype(np.float32)[:, :, None] + t  # [C, R, S]
    np.maximum(radii, 0.0, out=radii)
    cu = ell.centre[:, 0].astype(np.float32)[:, None, None]
    cv = ell.centre[:, 1].astype(np.float32)[:, None, None]
    u = cu + radii * cos
    v = cv + radii * sin
    C, R, S = radii.shape
    sizes = np.array([im.shape for im in images], dtype=np.float32)[owner]  # [C, 2] = (H, W)
    H, W = sizes[:, 0, None, None], sizes[:, 1, None, None]
    # A ray is a straight segment: it is inside the image when both of its ends are.
    if lo is None:
        ends_u, ends_v = u[..., [0, -1]], v[..., [0, -1]]
    else:
        ends = np.broadcast_to(np.stack([lo, S - 1 - lo], axis=1)[:, None, :], (C, R, 2))
        ends_u = np.take_along_axis(u, ends, axis=2)
        ends_v = np.take_along_axis(v, ends, axis=2)
    inside = np.all((ends_u >= 0) & (ends_u < W - 1) & (ends_v >= 0) & (ends_v < H - 1), axis=2)
    if own is not None:
        inside &= own
    if len(images) == 1:
        prof = _remap(images[0], u.reshape(C * R, S), v.reshape(C * R, S)).reshape(C, R, S)
    else:
        prof = np.empty((C, R, S), dtype=np.uint8)
        for k, rows in _image_rows(owner, len(images)):
            n = _count(rows) * R
            prof[rows] = _remap(images[k], u[rows].reshape(n, S),
                                v[rows].reshape(n, S)).reshape(-1, R, S)
    out = prof.astype(np.float32)
    # Negated profiles let the same code find light marks on a dark surface (per candidate).
    if isinstance(dark, np.ndarray):
        if not dark.all():
            out *= np.where(dark, 1.0, -1.0).astype(np.float32)[:, None, None]
    elif not dark:
        out = -out
    return out, radii, phi, inside


def _image_rows(owner: np.ndarray, n_images: int) -> list[tuple[int, slice | np.ndarray]]:
    """Each image that has candidates, with its candidates' rows: a slice when ``owner`` is in
    image order (as :func:`~mvpose_core.detect.assign.measure_all` gives it: views, no
    copies), else their indices."""
    if owner.size and bool((owner[1:] >= owner[:-1]).all()):
        bounds = np.searchsorted(owner, np.arange(n_images + 1)).tolist()
        return [(k, slice(bounds[k], bounds[k + 1])) for k in range(n_images)
                if bounds[k + 1] > bounds[k]]
    return [(k, rows) for k in range(n_images) if (rows := np.flatnonzero(owner == k)).size]


def _count(rows: slice | np.ndarray) -> int:
    return rows.stop - rows.start if isinstance(rows, slice) else int(rows.size)


def _remap(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at ``(u, v)`` (float32 ``[N, S]``), in chunks of rows that
    OpenCV's ``remap`` accepts (fewer than 32767)."""
    step = 32000
    if len(u) <= step:
        return cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.concatenate([
        cv2.remap(image, u[k : k + step], v[k : k + step], cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE)
        for k in range(0, len(u), step)
    ])


def _crossings(
    prof: np.ndarray, radii: np.ndarray, lo: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per ray: radius where the profile crosses its mid level, the ray's contrast, and validity.

    With ``lo``, candidate ``c`` uses only samples ``lo[c]`` to ``S - 1 - lo[c]`` of its rays
    (each candidate its own search length, the batch sampled over the longest).
    """
    S = prof.shape[-1]
    if lo is None:
        # np.add.reduce: the ufunc itself, without np.mean's Python wrapper (called per pass)
        inner = np.add.reduce(prof[..., :_LEVEL_SAMPLES], axis=-1) / _LEVEL_SAMPLES
        outer = np.add.reduce(prof[..., -_LEVEL_SAMPLES:], axis=-1) / _LEVEL_SAMPLES
    else:
        k = np.arange(_LEVEL_SAMPLES)
        shape = prof.shape[:2] + (_LEVEL_SAMPLES,)
        first = np.broadcast_to((lo[:, None] + k)[:, None, :], shape)
        last = np.broadcast_to((S - 1 - lo[:, None] - k)[:, None, :], shape)
        inner = np.add.reduce(np.take_along_axis(prof, first, axis=2), axis=-1) / _LEVEL_SAMPLES
        outer = np.add.reduce(np.take_along_axis(prof, last, axis=2), axis=-1) / _LEVEL_SAMPLES
    level = 0.5 * (inner + outer)
    above = prof >= level[..., None]
    # Upward crossings (inside -> outside) between samples j and j+1; keep the one nearest the
    # expected rim (the middle of the ray) so a nearby edge of something else does not capture it.
    up = ~above[..., :-1] & above[..., 1:]
    if lo is not None:
        j = np.arange(S - 1)
        up &= ((j >= lo[:, None]) & (j < S - 1 - lo[:, None]))[:, None, :]
    dist = np.where(up, np.abs(np.arange(S - 1) + 0.5 - (S - 1) / 2.0), np.inf)
    j = np.argmin(dist, axis=-1)
    flat = j + S * np.arange(j.size).reshape(j.shape)  # index of sample j of each ray
    p0 = prof.reshape(-1)[flat]
    p1 = prof.reshape(-1)[flat + 1]
    frac = np.clip((level - p0) / np.where(p1 != p0, p1 - p0, 1.0), 0.0, 1.0)
    edge_r = radii.reshape(-1)[flat] + _STEP * frac
    return edge_r, outer - inner, up.any(axis=-1)


def measure_many(
    image: np.ndarray,
    starts: list[Ellipse],
    dark: bool | np.ndarray,
    min_contrast: float,
    max_fit_residual_px: float,
    min_edge_fraction: float,
    search_px: float,
) -> list[Measurement]:
    """:func:`measure_in` for candidates of one image."""
    return measure_in(
        [image], np.zeros(len(starts), dtype=np.intp), starts, dark, min_contrast,
        max_fit_residual_px, min_edge_fraction, search_px,
    )


def measure_in(
    images: Sequence[np.ndarray],
    owner: np.ndarray,
    starts: list[Ellipse],
    dark: bool | np.ndarray,
    min_contrast: float,
    max_fit_residual_px: float,
    min_edge_fraction: float,
    search_px: float | np.ndarray,
) -> list[Measurement]:
    """Sub-pixel edge points and the ellipse through them, for many candidates at once.

    Candidate ``k`` starts from ``starts[k]`` in ``images[owner[k]]``: the candidates of several
    images (the cameras of one trigger) are measured together. Two passes: 16 rays searching
    ± ``search_px`` (one for all, or one per candidate; rounded up to the 0.5 px sample step)
    around the start ellipse locate the rim; then 32-96 rays (one per 1.5 px of rim or closer,
    of the largest candidate of the image) within ± 3 px of that rim give the final edge points and
    fit. Every step is one array operation over all candidates, images with different ray counts
    too (each candidate's rays its own, :func:`_mixed_grid`; a Python loop per candidate, or per
    image, would cost more than the arithmetic).
    A candidate's result depends on its ``search_px`` and its image's candidates only, not on
    the other images of the batch.
    """
    if not starts:
        return []
    C = len(starts)
    ell = Ellipses.of(starts)
    failed = np.zeros(C, dtype=int)  # 0 = fine, else 1 + index into _FAILURES
    steps = np.ceil(np.broadcast_to(np.asarray(search_px, dtype=float), (C,)) / _STEP - 1e-9)
    steps = steps.astype(np.intp)  # each candidate's half search length in samples
    lo = steps.max() - steps  # where each candidate's own ray starts in the batch's samples
    span = lo if lo.any() else None  # None: every candidate uses the whole ray
    # Fine rays ~1.5 px of rim apart for the largest candidate of each image (32 ... 96).
    radius = ell.radius
    if len(images) == 1:
        n_fine = np.full(C, _fine_rays(float(radius.max())))
    else:
        n_fine = np.empty(C, dtype=int)
        for _, rows in _image_rows(owner, len(images)):
            n_fine[rows] = _fine_rays(float(radius[rows].max()))
    ell, failed, *_ = _pass(images, owner, ell, failed, 16, _STEP * float(steps.max()), span,
                            dark, min_contrast, min_edge_fraction)
    # One pass for every candidate, each image with its own ray count (usually one for all:
    # the cameras of a station are alike).
    counts = n_fine if np.any(n_fine != n_fine[0]) else int(n_fine[0])
    ell, failed, residual, npts, contrast = _fine(
        images, owner, ell, failed, counts, dark, min_contrast, min_edge_fraction,
        max_fit_residual_px)
    return [
        Measurement(
            ell[c] if failed[c] == 0 else None,
            _FAILURES[failed[c] - 1] if failed[c] else None,
            float(contrast[c]),
            float(residual[c]),
            int(npts[c]),
        )
        for c in range(C)
    ]


def _fine_rays(radius_px: float) -> int:
    """Rays about 1.5 px of rim apart, rounded up to a multiple of 16 (32 ... 96): the cameras of
    a station see their marks at somewhat different sizes, and one ray count for all of them
    measures every image of a trigger in one pass instead of one pass per size."""
    return int(min(max(16 * np.ceil(4.0 * radius_px / 16.0), 32), _FINE_RAYS))


def _fine(
    images: Sequence[np.ndarray],
    owner: np.ndarray,
    ell: Ellipses,
    failed: np.ndarray,
    n_rays: int | np.ndarray,
    dark: bool | np.ndarray,
    min_contrast: float,
    min_edge_fraction: float,
    max_fit_residual_px: float,
) -> tuple[Ellipses, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The final pass (± 3 px of the rim found so far) and the fit's RMS residual check:
    ellipses, failure codes, residuals, edge point counts and contrasts."""
    ell, failed, pts, good, npts, contrast = _pass(
        images, owner, ell, failed, n_rays, 3.0, None, dark, min_contrast, min_edge_fraction)
    d = ell.distances(pts)
    residual = np.sqrt(np.sum(np.where(good, d * d, 0.0), axis=1) / np.maximum(npts, 1))
    failed = np.where((failed == 0) & ~(residual <= max_fit_residual_px), len(_FAILURES), failed)
    return ell, failed, residual, npts, contrast


def _pass(
    images: Sequence[np.ndarray],
    owner: np.ndarray,
    ell: Ellipses,
    failed: np.ndarray,
    n_rays: int | np.ndarray,
    half: float,
    span: np.ndarray | None,
    dark: bool | np.ndarray,
    min_contrast: float,
    min_edge_fraction: float,
) -> tuple[Ellipses, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One measuring pass: edge points on ``n_rays`` rays (one count for all, or per candidate),
    the fit, the checks.

    Returns the ellipses (the fitted ones where the candidate is still fine, else as given),
    the failure codes (earlier failures stick), and the pass's edge points, their validity,
    their count and the contrast per candidate.
    """
    prof, radii, phi, inside = _rays(images, owner, ell, n_rays, half, dark, span)
    edge_r, ray_contrast, crossed = _crossings(prof, radii, span)
    if isinstance(n_rays, int):
        cos, sin = _ray_grid(n_rays, half)[1:3]
        contrast = _row_median(ray_contrast)
    else:  # the median of each candidate's own rays (the others stand in as ±inf)
        _, cos, sin, _, pad = _mixed_grid(tuple(n_rays.tolist()))
        contrast = _row_median(np.where(np.isfinite(pad), ray_contrast, pad))
    good = inside & crossed & (ray_contrast > 0.5 * contrast[:, None])
    npts = good.sum(axis=1)
    pts = np.stack(
        [
            ell.centre[:, 0, None] + edge_r * cos[..., 0],
            ell.centre[:, 1, None] + edge_r * sin[..., 0],
        ],
        axis=2,
    )
    fitted = fit_ellipses(pts, good)
    # The first failing check names the reason (order of _FAILURES); earlier failures stick.
    checks = np.stack(
        [
            inside.sum(axis=1) < min_edge_fraction * n_rays,
            contrast < min_contrast,
            npts < min_edge_fraction * n_rays,
            ~fitted.ok,
        ]
    )
    first = np.where(checks.any(axis=0), np.argmax(checks, axis=0) + 1, 0)
    failed = np.where(failed > 0, failed, first)
    ok = (fitted.ok & (failed == 0))[:, None]
    ell = Ellipses(
        np.where(ok, fitted.centre, ell.centre),
        np.where(ok[:, 0], fitted.a, ell.a),
        np.where(ok[:, 0], fitted.b, ell.b),
        np.where(ok[:, 0], fitted.angle, ell.angle),
    )
    return ell, failed, pts, good, npts, contrast


def _row_median(x: np.ndarray) -> np.ndarray:
    """``np.median(x, axis=1)`` for a 2-D array, with a tenth of its fixed overhead."""
    n = x.shape[1]
    k = n // 2
    if n % 2:
        return np.partition(x, k, axis=1)[:, k]
    part = np.partition(x, (k - 1, k), axis=1)
    return 0.5 * (part[:, k - 1] + part[:, k])


_FAILURES = ("at image border", "low contrast", "incomplete edge", "shape", "shape")


def measure(
    image: np.ndarray,
    start: Ellipse,
    dark: bool | np.ndarray,
    min_contrast: float,
    max_fit_residual_px: float,
    min_edge_fraction: float,
    search_px: float,
) -> Measurement:
    """:func:`measure_many` for one candidate."""
    return measure_many(
        image, [start], dark, min_contrast, max_fit_residual_px, min_edge_fraction, search_px
    )[0]
