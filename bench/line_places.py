"""The trigger's work alone at each place of the station bench's moving part, stage by stage.

``python -m bench.line_places [--rounds N] [--polled]``: station 1's trigger work
(bench/stage_reference.py, on a thread at the trigger path's priority) with the part moved
through bench/moving_part.py's cycle of 8 places, as `python -m bench station` moves it; prints
each place's share of the tolerance and the median of each stage (ms). With ``--polled`` the
rounds alternate between a served station (`mvpose serve`) polled by the PLC twin every 1 ms at
its bench priority and no twin at all, and the medians of the two conditions are printed: what
the PLC's polls on the same two cores cost the work that does not serve them.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_station import N_POSES, station_file
from bench.moving_part import line_poses

STAGES = ("capture", "detect", "measure", "correct", "append", "processing")


def main(argv: list[str] | None = None) -> int:
    from bench.serve_process import start_serve
    from bench.stage_reference import AloneOnThread
    from bench.twin_process import TwinProcess

    ap = argparse.ArgumentParser(prog="python -m bench.line_places")
    ap.add_argument("--rounds", type=int, default=6, help="rounds over the 8 places (6)")
    ap.add_argument("--polled", action="store_true",
                    help="alternate a twin polling a served station every 1 ms with none")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        path = station_file("station1", tmp)
        serve = (start_serve(path, "station1", tmp / "served", extra_env={
            "MVPOSE_IMAGES_OK_EVERY": str(10**6), "MVPOSE_SIM_KEEP_POSES": str(N_POSES)})
            if args.polled else None)
        alone = AloneOnThread(path, tmp / "alone", keep_poses=N_POSES)
        poses = line_poses(alone.book.selected.config)  # type: ignore[union-attr]
        conds = ["polled", "quiet"] if args.polled else ["alone"]
        rows: dict[str, dict[int, list[dict[str, float]]]] = {
            c: {i: [] for i in range(len(poses))} for c in conds}
        try:
            for r in range(args.rounds + 1):  # the first round warms the renderings up
                for cond in conds if r % 2 == 0 else conds[::-1]:
                    twin = (TwinProcess(serve.plc_port, tmp / "twin.log", 50.0, 1.0, None)
                            if serve is not None and cond == "polled" else None)
                    try:
                        for i, pose in enumerate(poses):
                            alone.scene.set_part_pose(pose.T_rf_from_pf)
                            out = alone.trigger()
                            if r:
                                rows[cond][i].append(out)
                            time.sleep(0.05)
                    finally:
                        if twin is not None:
                            twin.close()
        finally:
            alone.close()
            if serve is not None:
                serve.stop()
    print(f"  station1, the trigger's work alone per place, {args.rounds} rounds; median ms")
    for cond in conds:
        print(f"  {cond}:")
        for i, pose in enumerate(poses):
            med = " ".join(f"{k} {np.median([o[k] for o in rows[cond][i]]):6.2f}"
                           for k in STAGES)
            print(f"    place {i} (share {pose.share:.2f}): {med}")
        every = [o for i in rows[cond] for o in rows[cond][i]]
        print("    all places: " + " ".join(f"{k} {np.median([o[k] for o in every]):6.2f}"
                                            for k in STAGES))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
