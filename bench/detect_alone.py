"""A trigger's images detected together (the trigger thread) or each alone (a detection worker).

``python -m bench.detect_alone [--rounds N]``: station 1's four simulated frames with the part at
its reference and moved by 0.25, 0.5 and 0.9 of the recipe's tolerance, the station's first
windows at the reference (no last part remembered). Per displacement, the CPU time of
:func:`~mvpose_core.detect.detect_marks_many` on the four images (what the trigger thread runs:
one measuring batch, and a part beyond the first windows followed from the blobs of every
image) and of :func:`~mvpose_core.detect.detect_marks` on each image in turn (what each detection
worker process runs, ``--detect-processes``: its own batch, and a displaced part followed from
its image's blobs only, else searched over the whole tolerance), alternating, medians.

From the two it prints the wall time ``w`` worker processes would take at best: the images
shared out over the workers, each worker's images one after the other, nothing else running and
no cost for handing a frame over. That is an upper bound on what workers can gain; the trigger
thread's figure is measured.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_station import station_file

SHARES = (0.0, 0.25, 0.5, 0.9)
WORKERS = (2, 3, 4)


def main(argv: list[str] | None = None) -> int:
    from bench.stage_reference import AloneStation
    from drivers.cameras import Frame
    from mvpose_core.detect import detect_marks, detect_marks_many
    from mvpose_core.synth import displaced
    from server.pipeline import PipelineOptions

    parser = argparse.ArgumentParser(prog="python -m bench.detect_alone")
    parser.add_argument("--rounds", type=int, default=60)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        alone = AloneStation(station_file("station1", tmp), tmp / "alone",
                             keep_poses=len(SHARES))
        try:
            rec = alone.book.selected.config  # type: ignore[union-attr]
            prior = rec.T_rf_from_pf0.matrix
            options = PipelineOptions().detect
            cams = list(alone.pipeline.view_cameras(1, None).values())
            print(f"  station1, {len(cams)} images a trigger, first windows at the reference; "
                  f"{args.rounds} rounds; CPU ms a trigger (median)")
            print(f"  {'share':>5} {'together':>9} {'each alone':>11} {'ratio':>6}   "
                  + "  ".join(f"{w} workers at best" for w in WORKERS))
            for share in SHARES:
                alone.scene.set_part_pose(displaced(rec, share) if share else prior)
                grabbed = alone.capture.grab_all(5.0)
                frames = []
                for cam in cams:
                    frame = grabbed[cam.camera_id]
                    assert isinstance(frame, Frame), frame
                    frames.append((frame.image, cam))
                together: list[float] = []
                each: list[list[float]] = [[] for _ in frames]
                for _ in range(args.rounds):
                    t0 = time.process_time()
                    joint = detect_marks_many(frames, rec, prior, options)
                    together.append(time.process_time() - t0)
                    single = []
                    for k, (image, cam) in enumerate(frames):
                        t0 = time.process_time()
                        single.append(detect_marks(image, cam, rec, prior, options))
                        each[k].append(time.process_time() - t0)
                found = (sum(d.found for dets in joint for d in dets),
                         sum(d.found for dets in single for d in dets))
                per_image = [float(np.median(e)) * 1e3 for e in each]
                tog = float(np.median(together)) * 1e3
                total = sum(per_image)
                best = [_shared_out(per_image, w) for w in WORKERS]
                print(f"  {share:5.2f} {tog:9.2f} {total:11.2f} {total / tog:6.2f}   "
                      + "  ".join(f"{b:17.2f}" for b in best)
                      + f"   (marks found {found[0]} / {found[1]})", flush=True)
        finally:
            alone.close()
    return 0


def _shared_out(per_image: list[float], workers: int) -> float:
    """The longest worker's time when the images go to ``workers`` in turn, largest first."""
    loads = [0.0] * max(1, min(workers, len(per_image)))
    for ms in sorted(per_image, reverse=True):
        loads[loads.index(min(loads))] += ms
    return max(loads) if per_image else math.nan


if __name__ == "__main__":
    raise SystemExit(main())
