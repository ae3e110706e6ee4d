"""An MES polling the station over REST, in a process of its own, for the station benchmark.

``python -m bench.mes_load BASE_URL TOKEN`` reads commands from stdin, one a line:

- ``rate R``: send R requests per second from now on (0: stop); an open-loop schedule served by
  a few client threads, so a slow answer does not lower the rate it was asked for;
- ``report``: print one JSON line with what was sent since the last report: requests, errors,
  the rate achieved and the median/p99 response time per kind of request.

The mix is what an MES polls: the newest page of measurements (50 summaries), the station's
live status (which the API asks the station process for, over its control channel), and the
detail of a recent record (detections, timings, offset).
"""

from __future__ import annotations

import json
import queue
import sys
import threading
import time

import httpx
import numpy as np

KINDS = ("page", "status", "detail")
WORKERS = 16  # enough that slow answers on a loaded host do not cap the rate


def main(argv: list[str]) -> int:
    base, token = argv[0], argv[1]
    ticks: queue.Queue[float] = queue.Queue()
    lock = threading.Lock()
    took: dict[str, list[float]] = {k: [] for k in KINDS}
    counts = {"sent": 0, "errors": 0}
    ids: list[int] = []
    rate = [0.0]
    wake = threading.Event()

    def worker(k: int) -> None:
        with httpx.Client(base_url=base, headers={"Authorization": "Bearer " + token},
                          timeout=10) as c:
            n = k
            while True:
                ticks.get()
                kind = KINDS[n % len(KINDS)]
                n += 1
                if kind == "detail" and not ids:
                    kind = "page"
                path = {"page": "/api/v1/measurements?limit=50",
                        "status": "/api/v1/station/status",
                        "detail": f"/api/v1/measurements/{ids[-1] if ids else 0}"}[kind]
                t = time.perf_counter()
                err = 0
                try:
                    r = c.get(path)
                    err = r.status_code >= 400
                    if kind == "page" and not err:
                        items = r.json()["items"]
                        if items:
                            ids.append(int(items[min(5, len(items) - 1)]["id"]))
                            del ids[:-10]
                except (httpx.HTTPError, ValueError, KeyError):
                    err = 1
                ms = (time.perf_counter() - t) * 1e3
                with lock:
                    took[kind].append(ms)
                    counts["sent"] += 1
                    counts["errors"] += int(err)

    def schedule() -> None:
        t_next = time.monotonic()
        while True:
            if rate[0] <= 0:
                wake.wait()
                wake.clear()
                t_next = time.monotonic()
                continue
            ticks.put(t_next)
            t_next += 1.0 / rate[0]
            delay = t_next - time.monotonic()
            if delay > 0:
                wake.wait(delay)
                if wake.is_set():
                    wake.clear()
                    t_next = time.monotonic()

    for k in range(WORKERS):
        threading.Thread(target=worker, args=(k,), daemon=True).start()
    threading.Thread(target=schedule, daemon=True).start()
    since = time.monotonic()
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "rate":
            rate[0] = float(cmd[1])
            if rate[0] <= 0:  # what was scheduled and not yet sent is dropped
                while not ticks.empty():
                    ticks.get_nowait()
            wake.set()
        elif cmd[0] == "report":
            now = time.monotonic()
            with lock:
                out = {"sent": counts["sent"], "errors": counts["errors"],
                       "seconds": now - since, "backlog": ticks.qsize(),
                       "ms": {k: [float(np.median(v)), float(np.percentile(v, 99)), len(v)]
                              for k, v in took.items() if v}}
                for v in took.values():
                    v.clear()
                counts["sent"] = counts["errors"] = 0
            since = now
            print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
