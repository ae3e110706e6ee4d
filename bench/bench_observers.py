"""Observers during a trigger storm: an open Live page, a subscribed OPC UA client, an open line
view, an open live camera view.

Issue 17: "an open Live page during a trigger storm does not move the station's p99"; issue 18:
"an OPC UA client subscribed during a trigger storm does not move the Modbus path's p99 by more
than 10 %"; issue 27: "an open line view and an open live camera view each raise the station's
trigger p99 by at most 10 %".

What runs, each in a process of its own: `mvpose serve` on station1 (deadline 1 s, as in
bench_station, so a slow trigger on a loaded host stays a sample, not a NOK with archived
frames; frames of OK results archived at the default 1 in 10, so the Live page has new images to
load) with its OPC UA link enabled (security "None", anonymous readers: a bench on loopback, no
certificates); the PLC twin (bench/twin_process.py, one Modbus/TCP connection, triggers back to
back, status read every 1 ms, trigger written -> RESULT_VALID read measured there).

The observers, in the bench process and Debian's Chromium:
  live   the operator page's Live view (/, logged in with the token) open in headless Chromium
         (Playwright), its server-sent events connected; each pushed result counted in the page;
  line   the line view (/line, logged in) open in headless Chromium; it polls its fragment
         every 2 s, so its block starts just before a refresh is due (each block holds one);
         each refresh during the blocks counted;
  cameras the live camera view (/cameras, logged in as the bootstrap engineer) open in headless
         Chromium: the API asks the station for a frame set every 0.5 s, the station grabs
         between triggers (preempted by a trigger), downscales and encodes 4 JPEGs; each frame
         set the page shows counted, and the station's own tally (grabs, camera previews
         preempted, sets skipped because a trigger ran) printed;
  opcua  an asyncua Client (anonymous, security None) subscribed to the MvposeResultReadyEvent
         of the VisionSystem (publishing interval 50 ms); each event counted. It does not call
         load_data_type_definitions: asyncua 1.x fails on some of the Machine Vision structures
         (ResultDataType, RecipeTransferOptions: "Unknown datatype for field") and only logs it.
Between blocks an observer is closed (page closed / client disconnected): the baseline has no
observer at all. Conditions come in alternating blocks (base, live, opcua, line, cameras, then
the same backwards, ...)
within one server, so a host that gets busier or quieter counts the same for every condition.
The observers run on the same host as the server (2 shared cores here): their own CPU counts
against the station, which a screen or a SCADA client on another machine would not.

Printed per run and condition: p50 / p99 of the roundtrip, the ratio observer / baseline of p99
(issue 18's and 27's target 1.10; issue 17 gives no number, the same 1.10 is shown beside it),
each with OK or MISSED; over all
runs the p50 ratio and the CPU the station, the API process and the OPC UA link's own process
(drivers.links.process) spent per trigger in each condition (what the observer costs the server,
apart from the host's noise in p99). A missed
target is printed as "MISSED"; the exit status is non-zero only when something failed.

Environment: MVPOSE_BENCH_OBS_RUNS (fresh servers, default 2), MVPOSE_BENCH_OBS_ROUNDS (rounds of
the ten blocks per run, default 3: 6 blocks per condition),
MVPOSE_BENCH_OBS_BLOCK (triggers per block, default 50).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import urllib.request
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bench.serve_process import cpu_s
from bench.twin_process import TwinProcess
from server.station.client import StationClient, StationDownError
from server.web.line import POLL_S as LINE_POLL_S

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "mvp_bench-observers-token-00000000000000000000"
RUNS = int(os.environ.get("MVPOSE_BENCH_OBS_RUNS", "2"))
ROUNDS = int(os.environ.get("MVPOSE_BENCH_OBS_ROUNDS", "3"))
BLOCK = int(os.environ.get("MVPOSE_BENCH_OBS_BLOCK", "50"))
CONDITIONS = ("base", "live", "opcua", "line", "cameras")
OBSERVERS = CONDITIONS[1:]
ORDER = (*CONDITIONS, *reversed(CONDITIONS))
#: each observer's line in the verdicts
LABELS = {"live": "issue 17: an open Live page",
          "opcua": "issue 18: a subscribed OPC UA client",
          "line": "issue 27: an open line view",
          "cameras": "issue 27: an open live camera view"}
TARGET_RATIO = 1.10
TWIN_PERIOD_MS = 0.0  # back to back
TWIN_POLL_MS = 1.0
#: a page refreshing on its own timer starts its block this long before its refresh is due
REFRESH_LEAD_S = 0.2


# --------------------------------------------------------------------------- the server
class Server:
    """`mvpose serve` (supervisor, station, API) on a temporary data dir, ports found at start."""

    def __init__(self, tmp: Path) -> None:
        data = yaml.safe_load((ROOT / "deploy" / "stations" / "station1.yaml").read_text())
        data["deadline_ms"] = 1000.0
        data.setdefault("links", {})["opcua"] = {
            "port": 0, "security": ["None"], "allow_anonymous": True}
        station = tmp / "station1.yaml"
        station.write_text(yaml.safe_dump(data, sort_keys=False))
        self.data_dir = tmp / "var"
        self.data_dir.mkdir()
        self.log = tmp / "serve.log"
        env = {**os.environ, "MVPOSE_BOOTSTRAP_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
        with self.log.open("wb") as out:
            self.proc = subprocess.Popen(  # noqa: S603 - our own interpreter and module
                [sys.executable, "-m", "server.cli", "serve", "--station", str(station),
                 "--data-dir", str(self.data_dir), "--host", "127.0.0.1", "--port", "0",
                 "--plc-host", "127.0.0.1", "--plc-port", "0", "--log-level", "warning"],
                cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
        self.client = StationClient(self.data_dir / "station.sock", timeout_s=2.0)
        t0 = time.monotonic()
        status = self._wait(lambda s: s["links"].get("opcua", {}).get("running"), 180.0)
        self.plc_port = int(status["links"]["modbus"]["port"])
        self.opcua_port = int(status["links"]["opcua"]["port"])
        self.station_pid = int(status["pid"])
        self.opcua_pid = int(status["links"]["opcua"]["pid"])  # the link's own process
        self.base_url = self._wait_api(60.0)
        self.api_pid = int(json.loads((self.data_dir / "api.json").read_text())["pid"])
        self.ready_s = time.monotonic() - t0

    def _tail(self) -> str:
        return self.log.read_text(errors="replace")[-3000:]

    def _wait(self, cond: Any, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mvpose serve exited with {self.proc.returncode}: "
                                   f"{self._tail()}")
            with contextlib.suppress(StationDownError):
                status = self.client.status().model_dump(mode="json")
                if cond(status):
                    return status
            time.sleep(0.2)
        raise TimeoutError(f"mvpose serve: station (with its OPC UA link) not ready within "
                           f"{timeout_s:.0f} s: {self._tail()}")

    def _wait_api(self, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                port = json.loads((self.data_dir / "api.json").read_text())["port"]
                url = f"http://127.0.0.1:{port}"
                with urllib.request.urlopen(url + "/api/v1/health/live", timeout=1.0):
                    return url
            except (OSError, ValueError, KeyError):
                time.sleep(0.2)
        raise TimeoutError(f"mvpose serve: API not ready within {timeout_s:.0f} s: {self._tail()}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _tree(root: int) -> set[int]:
    """``root`` and every process below it (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [root]
    while todo:
        pid = todo.pop()
        out.add(pid)
        todo += children.get(pid, [])
    return out


def observer_cpu(server: Server, twin: TwinProcess) -> dict[int, float]:
    """CPU s of the observers' side, per process: this one (key 0: Playwright's client, the
    asyncua thread) and its children apart from `mvpose serve` and the PLC twin (Playwright's
    driver, Chromium)."""
    others = _tree(os.getpid()) - _tree(server.proc.pid) - {twin.proc.pid, os.getpid()}
    return {0: time.process_time(), **{pid: cpu_s(pid) for pid in others}}


def _spent(before: dict[int, float], after: dict[int, float]) -> float:
    """CPU s between two readings; a process started in between counts from 0, one that ended
    in between is left out (Chromium's renderer of a page closed just before the block)."""
    return sum(t - before.get(pid, 0.0) for pid, t in after.items())


# --------------------------------------------------------------------------- the observers
class Browser:
    """Headless Chromium with a logged-in context (the bootstrap engineer's token)."""

    def __init__(self, base_url: str) -> None:
        from playwright.sync_api import sync_playwright

        from server.web.screenshots import VIEWPORT, launch, login

        self.base = base_url
        self._pw = sync_playwright().start()
        self.browser = launch(self._pw)
        self.context = self.browser.new_context(viewport=VIEWPORT)
        page = self.context.new_page()
        login(page, base_url, TOKEN)  # the session cookie stays in the context
        page.close()
        self.errors: list[str] = []

    def shutdown(self) -> None:
        with contextlib.suppress(Exception):
            self.browser.close()
        self._pw.stop()


class BrowserView:
    """One page of the operator page, opened and closed between blocks.

    A page that refreshes on a timer of its own (``period_s``: the line view polls every
    2 s) would mostly sit idle through a block of back-to-back triggers (~0.5 s); its block
    starts just before its next refresh is due instead, so that each block holds one."""

    def __init__(self, browser: Browser, path: str, ready_js: str, count_js: str,
                 counted_js: str, period_s: float = 0.0) -> None:
        self.b = browser
        self.path, self.ready_js, self.count_js, self.counted_js = (
            path, ready_js, count_js, counted_js)
        self.period_s = period_s
        self.page: Any = None
        self._due = 0.0  # when the next refresh is due (time.monotonic)
        self._before = 0  # updates shown before the block

    def open(self) -> None:
        self.page = self.b.context.new_page()
        self.page.on("pageerror", lambda err: self.b.errors.append(f"{self.path}: {err}"))
        self.page.goto(self.b.base + self.path)
        self.page.wait_for_function(self.ready_js, timeout=30000)
        self.page.evaluate(self.count_js)
        self._before = 0
        if self.period_s:  # its first refresh: the next one comes a period later
            self.page.wait_for_function(f"({self.counted_js}) >= 1",
                                        timeout=int(3000 * self.period_s))
            self._due = time.monotonic() + self.period_s

    def settle(self, default_s: float) -> None:
        """Wait before the block: ``default_s`` for the page to settle, or until just before
        its next refresh."""
        if not self.period_s:
            time.sleep(default_s)
            return
        time.sleep(max(0.0, self._due - REFRESH_LEAD_S - time.monotonic()))
        self._before = int(self.page.evaluate(self.counted_js))

    def close(self) -> int:
        """Close the page; the updates it showed during the block."""
        n = int(self.page.evaluate(self.counted_js)) - self._before
        self.page.close()
        self.page = None
        return n


def live_page(browser: Browser) -> BrowserView:
    """The Live view; counts the result fragments it swaps in (one per pushed "result")."""
    return BrowserView(browser, "/", "document.getElementById('live').dataset.connected === '1'",
                       """() => {
        window.__results = 0;
        new MutationObserver((changes) => {
            for (const c of changes) {
                for (const n of c.addedNodes) { if (n.id === 'result') window.__results += 1; }
            }
        }).observe(document.getElementById('live'), {childList: true, subtree: true});
    }""", "window.__results")


def line_view(browser: Browser) -> BrowserView:
    """The line view; counts its refreshes (htmx swaps of its fragment)."""
    return BrowserView(browser, "/line", "document.querySelector('#verdict') !== null",
                       """() => {
        window.__swaps = 0;
        document.body.addEventListener('htmx:afterSwap', () => { window.__swaps += 1; });
    }""", "window.__swaps", period_s=LINE_POLL_S)


def camera_view(browser: Browser) -> BrowserView:
    """The live camera view; counts the frame sets it shows (after the first)."""
    return BrowserView(browser, "/cameras",
                       "Number(document.getElementById('camera-view').dataset.updates) > 0",
                       """() => {
        window.__sets0 = Number(document.getElementById('camera-view').dataset.updates);
    }""", "Number(document.getElementById('camera-view').dataset.updates) - window.__sets0")


class OpcUaObserver:
    """An asyncua Client on a loop of its own thread, subscribed to the result events."""

    def __init__(self, port: int) -> None:
        logging.getLogger("asyncua").setLevel(logging.ERROR)  # "revised values differ" etc.
        self.url = f"opc.tcp://127.0.0.1:{port}/mvpose"
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="opcua-observer",
                                       daemon=True)
        self.thread.start()
        self.client: Any = None
        self.events = 0

    def _run(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(60)

    def event_notification(self, event: Any) -> None:
        self.events += 1

    async def _open(self) -> None:
        from asyncua import Client

        from drivers.links.opcua import MV_URI, MVPOSE_URI

        client = Client(self.url, timeout=15)
        await client.connect()
        self.client = client
        mv = await client.get_namespace_index(MV_URI)
        own = await client.get_namespace_index(MVPOSE_URI)
        vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
        etype = await client.nodes.base_event_type.get_child(
            [f"{mv}:ResultReadyEventType", f"{own}:MvposeResultReadyEventType"])
        sub = await client.create_subscription(50, self)
        await sub.subscribe_events(vs, etype)

    async def _close(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            await client.disconnect()

    def open(self) -> None:
        self.events = 0
        self._run(self._open())

    def settle(self, default_s: float) -> None:
        """Wait ``default_s`` before the block: the subscription settles."""
        time.sleep(default_s)

    def close(self) -> int:
        self._run(self._close())
        return self.events

    def shutdown(self) -> None:
        with contextlib.suppress(Exception):
            self._run(self._close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


# --------------------------------------------------------------------------- one run
def _pct(a: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(a, dtype=float), q)) if a else float("nan")


def one_run(k: int, tmp: Path) -> dict[str, Any]:
    server = Server(tmp)
    twin = browser = opcua = None
    rt: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    seen = dict.fromkeys(OBSERVERS, 0)
    tally0 = tally1 = {}
    # station, API process, OPC UA link process, observers' side: CPU s during the blocks
    cpu = {c: [0.0, 0.0, 0.0, 0.0] for c in CONDITIONS}
    nok = 0
    try:
        twin = TwinProcess(server.plc_port, tmp / "twin.log", TWIN_PERIOD_MS, TWIN_POLL_MS)
        browser = Browser(server.base_url)
        opcua = OpcUaObserver(server.opcua_port)
        observers: dict[str, Any] = {"live": live_page(browser), "opcua": opcua,
                                     "line": line_view(browser), "cameras": camera_view(browser)}
        tally0 = server.client.status().part("camera_view") or {}
        twin.block(1, 30)  # warm-up, not counted
        next_id = 100
        for _ in range(ROUNDS):
            for cond in ORDER:
                obs = observers.get(cond)
                if obs is not None:
                    obs.open()
                    obs.settle(0.5)  # its start (page load, subscription) settles
                else:
                    time.sleep(0.5)
                c0 = (cpu_s(server.station_pid), cpu_s(server.api_pid),
                      cpu_s(server.opcua_pid), observer_cpu(server, twin))
                res = twin.block(next_id, BLOCK)
                cpu[cond][0] += cpu_s(server.station_pid) - c0[0]
                cpu[cond][1] += cpu_s(server.api_pid) - c0[1]
                cpu[cond][2] += cpu_s(server.opcua_pid) - c0[2]
                cpu[cond][3] += _spent(c0[3], observer_cpu(server, twin))
                next_id += BLOCK
                if obs is not None:
                    time.sleep(0.3)  # the last results reach the observer
                    seen[cond] += obs.close()
                rt[cond] += res["roundtrip_ms"]
                nok += int(res["nok"])
        tally1 = server.client.status().part("camera_view") or {}
        if browser.errors:
            raise RuntimeError(f"a page raised: {browser.errors[:3]}")
    finally:
        for obs in (browser, opcua):
            if obs is not None:
                obs.shutdown()
        if twin is not None:
            twin.close()
        server.stop()
    tally = {n: int(tally1.get(n, 0)) - int(tally0.get(n, 0))
             for n in ("requests", "grabs", "frames", "preempted", "skipped")}
    return {"run": k, "rt": rt, "seen": seen, "nok": nok, "ready_s": server.ready_s,
            "cpu": cpu, "camera_view": tally}


def report(runs: list[dict[str, Any]]) -> None:
    n_blocks = ROUNDS * ORDER.count("base")
    print(f"\n  trigger -> RESULT_VALID seen by the PLC twin (ms), triggers back to back, "
          f"{n_blocks} blocks of {BLOCK} per condition and run")
    print("    run   " + "   ".join(f"{c + ' p50':>11} {'p99':>6}" for c in CONDITIONS)
          + "   " + "  ".join(f"{c + '/base p99':>13}" for c in OBSERVERS))
    ratios: dict[str, list[float]] = {c: [] for c in OBSERVERS}
    for r in runs:
        rt = r["rt"]
        base99 = _pct(rt["base"], 99)
        for c in OBSERVERS:
            ratios[c].append(_pct(rt[c], 99) / base99)
        print(f"    {r['run']:3d}   "
              + "   ".join(f"{_pct(rt[c], 50):11.1f} {_pct(rt[c], 99):6.1f}" for c in CONDITIONS)
              + "   " + "  ".join(f"{ratios[c][-1]:13.2f}" for c in OBSERVERS))
        shown = ", ".join(f"{c} {r['seen'][c]}" for c in OBSERVERS)
        cv = r["camera_view"]
        print(f"          updates shown (live: results, opcua: events, line: refreshes, "
              f"cameras: frame sets) {shown}; station camera view: {cv['requests']} requests, "
              f"{cv['grabs']} frame sets grabbed, {cv['frames']} camera frames, "
              f"{cv['preempted']} camera previews preempted by a trigger, {cv['skipped']} sets "
              f"skipped (a trigger ran)")
    pooled = {c: [x for r in runs for x in r["rt"][c]] for c in CONDITIONS}
    print("    all   "
          + "   ".join(f"{_pct(pooled[c], 50):11.1f} {_pct(pooled[c], 99):6.1f}"
                       for c in CONDITIONS)
          + "   " + "  ".join(f"{_pct(pooled[c], 99) / _pct(pooled['base'], 99):13.2f}"
                              for c in OBSERVERS) + "   (pooled)")
    print("    per trigger, all runs: p50 observer / baseline "
          + ", ".join(f"{c} {_pct(pooled[c], 50) / _pct(pooled['base'], 50):.2f}"
                      for c in OBSERVERS)
          + "; CPU ms of the station / API process / OPC UA link process / observers' side "
            "(bench process, Playwright, Chromium) "
          + ", ".join(f"{c} " + " / ".join(
              f"{1e3 * sum(r['cpu'][c][i] for r in runs) / len(pooled[c]):.1f}" for i in range(4))
                      for c in CONDITIONS))
    noks = sum(r["nok"] for r in runs)
    print(f"    NOK answers: {noks}; server ready (OPC UA listening) after "
          + ", ".join(f"{r['ready_s']:.1f}" for r in runs) + " s")
    for c in OBSERVERS:
        rs = ratios[c]
        med = float(np.median(rs))
        verdict = "OK" if med <= TARGET_RATIO else "MISSED"
        print(f"  {LABELS[c]}: p99 observer / baseline, median of {len(rs)} runs {med:.2f} "
              f"(runs {min(rs):.2f}-{max(rs):.2f}), target <= {TARGET_RATIO:.2f} ... {verdict}")


def main() -> int:
    if not Path("/usr/bin/chromium").exists():
        print("bench_observers: /usr/bin/chromium is missing (Debian's chromium; `make test` "
              "installs it)")
        return 1
    runs = []
    try:
        for k in range(1, RUNS + 1):
            with tempfile.TemporaryDirectory(prefix="mvpose-bench-observers-") as t:
                t0 = time.monotonic()
                runs.append(one_run(k, Path(t)))
                print(f"  run {k}: {time.monotonic() - t0:.0f} s", flush=True)
    except Exception:  # noqa: BLE001 - one line of context, then the failure itself
        traceback.print_exc()
        print("bench_observers: failed (above); no numbers")
        return 1
    report(runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
