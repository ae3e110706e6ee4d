"""docs/calibration-walkthrough.md, every ``$ mvpose …`` command run as the guide writes it (with
fewer samples, see SMALLER), in a fresh folder: so the guide cannot rot. Each command must exit
0 and print what the guide shows it printing, line by line up to the first number."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path

import pytest
from stations import relaxed_deadline, station_file

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "calibration-walkthrough.md"
#: The guide's sizes, and the smaller ones this test runs (same commands otherwise). The fixed
#: station keeps its 14 placements: each camera needs six of its own for its intrinsics.
SMALLER = {"--samples 18": "--samples 10"}
#: Lines that name samples: which samples an outlier or a missed board falls on changes with
#: the set's size.
PER_SAMPLE = ("  left out", "  partly used", "  OUTLIER", "  WARNING", "  solver")


def walkthrough() -> list[tuple[str, list[str]]]:
    """(command, the output lines the guide shows) for every ``$ mvpose`` line of the section."""
    text = DOC.read_text()
    start = text.index("\n## Walkthrough")
    end = text.find("\n## ", start + 1)  # the section ends at the next one or the page's end
    end = len(text) if end < 0 else end
    steps: list[tuple[str, list[str]]] = []
    lines = text[start:end].splitlines()
    k = 0
    while k < len(lines):
        line = lines[k]
        k += 1
        if not line.startswith("$ mvpose "):
            continue
        cmd = line[2:]
        while cmd.endswith("\\"):
            cmd = cmd[:-1].rstrip() + " " + lines[k].strip()
            k += 1
        shown = []
        while k < len(lines) and not lines[k].startswith(("$ ", "```")):
            shown.append(lines[k])
            k += 1
        steps.append((cmd, shown))
    return steps


def _head(line: str) -> str:
    """A line up to its first number (and its sign): the part a different run prints alike."""
    return re.split(r"[-+]?\d", line, maxsplit=1)[0].rstrip()


def test_the_guide_has_a_walkthrough() -> None:
    cmds = [c for c, _ in walkthrough()]
    kinds = [shlex.split(c)[1:3] for c in cmds]
    for step in ("synthetic", "intrinsics", "stereo", "handeye", "station", "compare"):
        assert ["calibrate", step] in kinds, (step, cmds)
    # the acceptance's order: synthetic -> intrinsics -> hand-eye driven over Modbus -> verify
    # -> gauge study
    order = [kinds.index(k) for k in (["calibrate", "synthetic"], ["calibrate", "intrinsics"],
                                      ["calibrate", "rehearse-handeye"],
                                      ["calibrate", "rehearse-verify"])]
    gauge = next(i for i, k in enumerate(kinds) if k[:1] == ["gauge"])
    assert order == sorted(order) and order[-1] < gauge, cmds
    assert all(shown for _, shown in walkthrough()), "every command shows its output"


@pytest.mark.timeout(1800)
def test_the_walkthrough_runs_as_written(tmp_path: Path) -> None:
    (tmp_path / "deploy").symlink_to(ROOT / "deploy")
    # Station 1 and the lab with the relaxed deadline for the demo and the rehearsed hand-eye (as
    # the guide says): a loaded machine misses the 50 ms cycle deadline, and the gauge study
    # would find no OK measurement, the verify no pose.
    relaxed = station_file(tmp_path, "station1", relaxed_deadline)
    lab = station_file(tmp_path, "lab", relaxed_deadline)
    steps = []
    for cmd, shown in walkthrough():
        for big, small in SMALLER.items():
            cmd = cmd.replace(big, small)
        if cmd.startswith(("mvpose demo", "mvpose gauge")):
            cmd = cmd.replace("deploy/stations/station1.yaml", str(relaxed))
        if cmd.startswith("mvpose calibrate rehearse-handeye"):
            cmd = cmd.replace("deploy/stations/lab.yaml", str(lab))
        steps.append((cmd, shown))

    def run(cmd: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "server.cli", *shlex.split(cmd)[1:]],
                              cwd=tmp_path, capture_output=True, text=True, timeout=1500)

    # Steps that read nothing another wrote run side by side (the robot set's chain, the fixed
    # station's, the demo's): on a machine shared by many jobs their waits overlap.
    with ThreadPoolExecutor(max_workers=len(steps)) as pool:
        done: list[Future[subprocess.CompletedProcess[str]]] = []
        for k, (cmd, _) in enumerate(steps):
            first = [done[j] for j in after(k, [c for c, _ in steps])]
            done.append(pool.submit(lambda c=cmd, f=first: (wait(f), run(c))[1]))
    for (cmd, shown), future in zip(steps, done, strict=True):
        out = future.result()
        assert out.returncode == 0, (cmd, out.stdout[-2000:], out.stderr[-2000:])
        printed = {_head(line) for line in out.stdout.splitlines()}
        for line in shown:
            if _head(line) and not line.startswith(PER_SAMPLE) and "…" not in line:
                assert _head(line) in printed, (cmd, line, out.stdout[-3000:])


def after(k: int, cmds: list[str]) -> list[int]:
    """The earlier steps step ``k`` reads from: those that wrote (``--out``, ``--data-dir``) a
    file or folder named by one of its arguments or holding it."""
    def written(cmd: str) -> list[str]:
        args = shlex.split(cmd)
        return [args[i + 1] for i, a in enumerate(args[:-1]) if a in ("--out", "--data-dir")]

    reads = shlex.split(cmds[k])
    return [j for j in range(k) for w in written(cmds[j])
            if any(a == w or a.startswith(w.rstrip("/") + "/") for a in reads)]
