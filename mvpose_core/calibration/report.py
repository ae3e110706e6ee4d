"""Calibration reports in millimetres: per-sample residuals, 1σ, repeatability, outliers, a plot."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_core.calibration.handeye import HandEyeResult
from mvpose_core.calibration.intrinsics import IntrinsicsResult
from mvpose_core.calibration.joint import HandEyeProblem, refine
from mvpose_core.calibration.outliers import find_outliers
from mvpose_core.calibration.station import StationResult
from mvpose_core.calibration.stereo import StereoResult
from mvpose_core.transforms import (
    Array,
    invert,
    matrix_to_rotvec,
    matrix_to_xyzwpr,
    transform_error,
)


@dataclass(frozen=True)
class Repeatability:
    """Spread of the result when each sample in turn is left out (leave-one-out)."""

    method: str
    n: int
    std: dict[str, float]  # per quantity: standard deviation over the leave-one-out results
    max_dev: dict[str, float]  # per quantity: largest deviation from the all-samples result
    most_influential: str  # sample whose removal moves the result most
    runs: dict[str, dict[str, float]] = field(default_factory=dict)  # left-out sample → values


@dataclass(frozen=True)
class CalibrationReport:
    """Everything a commissioning engineer needs to judge a calibration, in px and mm."""

    kind: str
    per_sample_rms_px: dict[str, float]
    rms_px: float
    working_distance_mm: float
    error_mm_at_working_distance: float  # rms_px seen as a lateral error at that distance
    outliers: list[str]
    rejected: dict[str, str]
    sigma: dict[str, float] = field(default_factory=dict)  # 1σ from the covariance
    result: dict[str, Any] = field(default_factory=dict)  # headline numbers (f, baseline, ...)
    methods: dict[str, str] = field(default_factory=dict)  # hand-eye solver cross-check
    repeatability: Repeatability | None = None
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def text(self) -> str:
        """A short human-readable summary (the CLI prints it)."""
        lines = [
            f"{self.kind}: {len(self.per_sample_rms_px)} samples used, "
            f"{len(set(self.rejected) - set(self.per_sample_rms_px))} left out",
            f"  reprojection RMS {self.rms_px:.3f} px = {self.error_mm_at_working_distance:.3f} mm "
            f"at the working distance {self.working_distance_mm:.0f} mm",
        ]
        lines += [f"  1σ {k}: {v:.2g}" for k, v in self.sigma.items()]
        lines += [f"  {k}: {_fmt(v)}" for k, v in self.result.items()]
        if self.repeatability:
            r = self.repeatability
            spread = ", ".join(f"{k} {v:.2g}" for k, v in r.max_dev.items())
            lines.append(
                f"  {r.method} ({r.n} runs): largest change {spread} (sample {r.most_influential})"
            )
        for name, status in self.methods.items():
            lines.append(f"  solver {name}: {status}")
        for sid in self.outliers:
            lines.append(f"  OUTLIER sample {sid}: {self.per_sample_rms_px[sid]:.3f} px")
        for sid, why in self.rejected.items():
            # A sample some cameras missed is still used with the others (see build_problem).
            used = sid in self.per_sample_rms_px
            lines.append(f"  {'partly used' if used else 'left out'} sample {sid}: {why}")
        lines += [f"  WARNING {w}" for w in self.warnings]
        return "\n".join(lines)


def _fmt(v: Any) -> str:
    # Values arrive rounded to their 1σ (see :func:`rounded`); print them as they are held.
    return repr(v) if isinstance(v, float) else str(v)


def leave_one_out(
    ids: Sequence[str], solve: Callable[[list[str]], dict[str, float]], full: dict[str, float]
) -> Repeatability:
    """Re-solve without each sample and compare every quantity with its value in ``full``."""
    runs = {sid: solve([s for s in ids if s != sid]) for sid in ids}
    keys = list(full)
    dev = {k: np.array([abs(runs[s][k] - full[k]) for s in ids]) for k in keys}
    vals = {k: np.array([runs[s][k] for s in ids]) for k in keys}
    total = sum(dev[k] / (dev[k].max() or 1.0) for k in keys)
    return Repeatability(
        method="leave-one-out",
        n=len(ids),
        std={k: float(np.std(vals[k], ddof=1)) for k in keys},
        max_dev={k: float(dev[k].max()) for k in keys},
        most_influential=ids[int(np.argmax(total))],
        runs=runs,
    )


# --------------------------------------------------------------------------- per calibration kind


def handeye_report(
    problem: HandEyeProblem, result: HandEyeResult, loo: bool = True
) -> CalibrationReport:
    """Report of a hand-eye calibration: the values the calibration file holds, each with as
    many digits as its 1σ needs; the 1σ of the weighted adjustment first, the leave-one-out
    jackknife (the adjustment re-run without each sample, weights held) beside it."""
    name = "T_gf_from_cf" if result.mount == "robot" else "T_rf_from_cf"
    ref = result.reference
    f = result.cameras[ref].fx
    rep = None
    warnings = list(result.warnings)
    sd = np.sqrt(np.diag(result.cov))
    sigma: dict[str, float] = {
        f"{name} translation mm": _sig(result.sigma_mm),
        f"{name} rotation deg": _sig(result.sigma_deg),
    }
    ids = sorted(result.per_sample_rms_px)
    if loo and len(ids) >= 4:

        def solve(subset: list[str]) -> dict[str, float]:
            r = refine(
                problem, result.X, result.Y, subset, result.weights, estimate=False,
                intrinsics=result.intrinsics_refined,
            )  # fmt: skip
            deg, mm = transform_error(r.X, result.X)
            dt = r.X[:3, 3] - result.X[:3, 3]
            dr = np.degrees(matrix_to_rotvec(r.X[:3, :3] @ result.X[:3, :3].T))
            return {"hand_eye_mm": mm, "hand_eye_deg": deg, **_components(dt, dr)}

        rep = leave_one_out(ids, solve, {"hand_eye_mm": 0.0, "hand_eye_deg": 0.0})
        n = len(ids)
        for part, p in (("translation mm", "t"), ("rotation deg", "r")):
            v = np.array([[rep.runs[s][f"{p}{a}"] for a in "xyz"] for s in ids])
            ss = float(np.sum((v - v.mean(axis=0)) ** 2))
            sigma[f"{name} {part} (jackknife)"] = _sig(float(np.sqrt((n - 1) / n * ss)))
        warnings += _jackknife_warning(sigma, name, n)
    w = result.weights
    sigma["detector noise px (from residuals)"] = _sig(w.px)
    sigma["robot pose per axis mm (from the fit)"] = _sig(w.robot_mm)
    sigma["robot pose per axis deg (from the fit)"] = _sig(w.robot_deg)
    wpr = matrix_to_xyzwpr(result.X)[3:]
    values: dict[str, Any] = {
        f"{name} xyz mm": [
            rounded(float(v), s) for v, s in zip(result.X[:3, 3], sd[3:6], strict=True)
        ],
        f"{name} wpr deg": [rounded(float(v), float(np.degrees(sd[:3].max()))) for v in wpr],
        "board scale from the robot motion": f"{rounded(result.scale, result.scale_sigma)} ± "
        f"{_sig(result.scale_sigma)}",
        "robot pose σ stated per axis": f"{result.stated.robot_mm:g} mm / "
        f"{result.stated.robot_deg:g}°",
    }
    values.update(_camera_values(result.cameras, result.camera_sigma))
    for cid in result.cameras:
        if cid != ref:
            values[f"{cid} baseline to {ref} mm"] = round(
                float(np.linalg.norm(invert(result.T_cfc_from_cf0[cid])[:3, 3])), 4
            )
    if result.robot_corrections:
        worst = max(
            result.robot_corrections, key=lambda s: np.linalg.norm(result.robot_corrections[s][3:])
        )
        c = result.robot_corrections[worst]
        values["largest flange correction"] = (
            f"sample {worst}: {np.linalg.norm(c[3:]):.3f} mm / {np.linalg.norm(c[:3]):.4f}°"
        )
    rejected = dict(result.rejected)
    rejected.update({sid: f"outlier: {why}" for sid, why in result.left_out.items()})
    return CalibrationReport(
        kind=f"handeye ({result.mount})",
        per_sample_rms_px=result.per_sample_rms_px,
        rms_px=result.rms_px,
        working_distance_mm=result.depth_mm,
        error_mm_at_working_distance=result.rms_px * result.depth_mm / f,
        outliers=find_outliers(result.per_sample_rms_px),
        rejected=rejected,
        sigma=sigma,
        result=values,
        methods={k: v.status for k, v in result.methods.items()},
        repeatability=rep,
        warnings=warnings,
    )


#: A jackknife 1σ this many times the adjustment's is beyond its sampling spread (≈ 35 % at
#: 18 samples): the samples scatter more than the model's errors explain.
JACKKNIFE_EXCESS = 2.0


def _jackknife_warning(sigma: dict[str, float], name: str, n: int) -> list[str]:
    ratios = [
        sigma[f"{name} {part} (jackknife)"] / sigma[f"{name} {part}"]
        for part in ("translation mm", "rotation deg")
        if sigma[f"{name} {part}"] > 0
    ]
    worst = max(ratios, default=0.0)
    if worst <= JACKKNIFE_EXCESS:
        return []
    return [
        f"the leave-one-out 1σ is {worst:.1f}× the adjustment's over {n} samples: the samples "
        "scatter more than the pixel noise and the robot σ explain (a robot less accurate than "
        "stated: give --robot-sigma; or image errors repeated within an image: blur, a bent "
        "board); the station takes the jackknife figure for this calibration"
    ]


def rounded(value: float, sigma: float) -> float:
    """``value`` with as many decimals as its 1σ needs (two significant digits of the σ)."""
    if not (np.isfinite(sigma) and sigma > 0):
        return value
    return round(value, int(np.clip(1 - np.floor(np.log10(sigma)), 0, 12)))


def _sig(sigma: float) -> float:
    """A 1σ to two significant digits."""
    if not (np.isfinite(sigma) and sigma > 0):
        return sigma
    return float(f"{sigma:.2g}")


def _components(dt: Array, dr: Array) -> dict[str, float]:
    return {
        **{f"t{a}": float(v) for a, v in zip("xyz", dt, strict=True)},
        **{f"r{a}": float(v) for a, v in zip("xyz", dr, strict=True)},
    }


def intrinsics_report(
    res: IntrinsicsResult, solve: Callable[[list[str]], IntrinsicsResult] | None = None
) -> CalibrationReport:
    """Report of a camera calibration; ``solve`` re-calibrates a subset for leave-one-out."""
    depth = float(np.median([T[2, 3] for T in res.T_cf_from_bf.values()]))
    cam = res.camera
    rep = None
    if solve is not None and len(res.used) >= 7:
        rep = leave_one_out(res.used, lambda s: _intr_numbers(solve(s)), _intr_numbers(res))
    return CalibrationReport(
        kind=f"intrinsics ({res.camera_id})",
        per_sample_rms_px=res.per_sample_rms_px,
        rms_px=res.rms_px,
        working_distance_mm=depth,
        error_mm_at_working_distance=res.rms_px * depth / cam.fx,
        outliers=find_outliers(res.per_sample_rms_px),
        rejected=dict(res.rejected),
        sigma={f"{k} (OpenCV)": v for k, v in res.std.items() if k in ("fx", "fy", "cx", "cy")},
        result={
            **{
                f"{k} px": rounded(float(getattr(cam, k)), res.std.get(k, float("nan")))
                for k in ("fx", "fy", "cx", "cy")
            },
            "distortion": [round(float(x), 6) for x in cam.dist],
        },
        repeatability=rep,
    )


def _intr_numbers(r: IntrinsicsResult) -> dict[str, float]:
    return {"fx px": r.camera.fx, "cx px": r.camera.cx, "cy px": r.camera.cy}


def _camera_values(cameras: Mapping[str, Any], sds: Mapping[str, Array]) -> dict[str, Any]:
    """Each camera's intrinsics as the file holds them, with the digits their 1σ needs
    (unrounded, marked *(held)*, where they were not adjusted)."""
    values: dict[str, Any] = {}
    for cid, cam in cameras.items():
        sd = sds.get(cid)
        held = "" if sd is not None else " (held)"
        for k, key in enumerate(("fx", "fy", "cx", "cy")):
            x = float(getattr(cam, key))
            values[f"{cid} {key} px{held}"] = rounded(x, float(sd[k])) if sd is not None else x
        values[f"{cid} distortion{held}"] = [
            rounded(float(d), float(sd[4 + k])) if sd is not None else float(d)
            for k, d in enumerate(cam.dist)
        ]
    return values


def stereo_report(
    res: StereoResult, depth_mm: float, solve: Callable[[list[str]], StereoResult] | None = None
) -> CalibrationReport:
    """Report of a stereo calibration: the 1σ of the second camera's pose in the first's (from
    the images-only adjustment's covariance, intrinsics included when they were refined) first,
    then the values the file holds and the leave-one-out spread of the baseline."""
    rep = None
    ids = sorted(res.per_sample_rms_px)
    if solve is not None and len(ids) >= 6:
        rep = leave_one_out(
            ids, lambda s: {"baseline mm": solve(s).baseline_mm}, {"baseline mm": res.baseline_mm}
        )
    name = "T_cf1_from_cf2"
    T = invert(res.T_cf2_from_cf1)
    return CalibrationReport(
        kind=f"stereo ({res.camera1}/{res.camera2})",
        per_sample_rms_px=res.per_sample_rms_px,
        rms_px=res.rms_px,
        working_distance_mm=depth_mm,
        error_mm_at_working_distance=res.rms_px * depth_mm / res.model1.fx,
        outliers=find_outliers(res.per_sample_rms_px),
        rejected=dict(res.rejected),
        sigma={
            f"{name} translation mm": _sig(res.sigma_mm),
            f"{name} rotation deg": _sig(res.sigma_deg),
            "baseline mm": _sig(res.sigma_baseline_mm),
        },
        result={
            "baseline mm": rounded(res.baseline_mm, res.sigma_baseline_mm),
            f"{name} xyz mm ({res.camera2} in {res.camera1})": [
                rounded(float(x), res.sigma_mm) for x in T[:3, 3]
            ],
            **_camera_values({res.camera1: res.model1, res.camera2: res.model2}, res.intrinsics_sd),
        },
        repeatability=rep,
    )


def station_report(res: StationResult, depth_mm: float, fx: float) -> CalibrationReport:
    """Report of a fixed-station calibration: per camera the 1σ of its pose relative to its
    group's reference camera (images-only adjustment) and in RF (with the group's placement,
    jackknife over the placements); the camera groups and how well the robot-frame
    measurements agree with the rigid station."""
    v = np.array(list(res.per_sample_rms_px.values()))
    rms = float(np.sqrt(np.mean(v**2)))
    sigma: dict[str, float] = {}
    for g in res.groups:
        for c in g.T_ref_from_cf:
            if c != g.reference:
                mm, deg = res.sigma_relative[c]
                sigma[f"{c} from {g.reference} translation mm"] = _sig(mm)
                sigma[f"{c} from {g.reference} rotation deg"] = _sig(deg)
    for c, (mm, deg) in res.sigma_rf.items():
        sigma[f"{c} in RF translation mm"] = _sig(mm)
        sigma[f"{c} in RF rotation deg"] = _sig(deg)
    sds = {c: sd for g in res.groups for c, sd in g.intrinsics_sd.items()}
    return CalibrationReport(
        kind="station (fixed cameras)",
        per_sample_rms_px=res.per_sample_rms_px,
        rms_px=rms,
        working_distance_mm=depth_mm,
        error_mm_at_working_distance=rms * depth_mm / fx,
        outliers=find_outliers(res.per_sample_rms_px),
        rejected=dict(res.rejected),
        sigma=sigma,
        result={
            "camera groups": [sorted(g.T_ref_from_cf) for g in res.groups],
            "RF placement RMS mm (per group)": {
                k: round(x, 3) for k, x in res.placement_rms_mm.items()
            },
            **{
                f"{c} xyz mm in RF": [rounded(float(x), res.sigma_rf[c][0]) for x in T[:3, 3]]
                for c, T in res.T_rf_from_cf.items()
            },
            **_camera_values(res.cameras, sds),
        },
    )


# --------------------------------------------------------------------------- plot


def save_residual_plot(
    path: str | Path, report: CalibrationReport, residuals: Mapping[str, Array] | None = None
) -> Path:
    """PNG: per-sample RMS (outliers red, the rest blue) and, if given, every residual vector."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if residuals else 1, 1)
    ids = list(report.per_sample_rms_px)
    vals = [report.per_sample_rms_px[i] for i in ids]
    colours = ["tab:red" if i in report.outliers else "tab:blue" for i in ids]
    ax.bar(range(len(ids)), vals, color=colours)
    ax.set_xticks(range(len(ids)), ids, rotation=90, fontsize=7)
    ax.set_ylabel("reprojection RMS [px]")
    ax.set_title(
        f"{report.kind}: RMS {report.rms_px:.3f} px = "
        f"{report.error_mm_at_working_distance:.3f} mm @ {report.working_distance_mm:.0f} mm",
        fontsize=9,
    )
    if residuals:
        ax2 = fig.add_subplot(1, 2, 2)
        for sid, r in residuals.items():
            ax2.plot(
                r[:, 0], r[:, 1], ".", ms=2, color="tab:red" if sid in report.outliers else None
            )
        lim = max(float(np.abs(np.concatenate(list(residuals.values()))).max()), 1e-3) * 1.1
        ax2.set_xlim(-lim, lim)
        ax2.set_ylim(-lim, lim)
        ax2.set_aspect("equal")
        ax2.set_xlabel("du [px]")
        ax2.set_ylabel("dv [px]")
        ax2.set_title("residuals of every corner", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
