"""The line view (/line) in a real browser, beside a real station process (simulated station 1).

Results come from real triggers over the control channel: with nothing in front of the cameras
the station answers NOK (frames archived), with the part at its taught place OK. The panel PC's
screen is 1366 x 768 (15.6"); screenshots go to var/screenshots/.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import stations
from axe import assert_accessible
from system_packages import ensure_commands

from mvpose_core.reasons import describe, what_to_check
from mvpose_core.shifts import DEFAULT_SHIFTS, shift_at, time_zone
from mvpose_core.station import load_station
from server.app import create_app
from server.auth import Role, create_token
from server.state import Services, open_services
from server.station.client import StationClient
from server.station.process import StationProcess
from server.web.screenshots import launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
PANEL = {"width": 1366, "height": 768}  # a 15.6" panel PC: 1567 px / 15.6 in ≈ 100 dpi
#: 9 mm letters (2 m away) on that panel: 9 mm × 100 px / 25.4 mm ≈ 35 px cap height
MIN_CAP_PX = 35


@dataclass
class Line:
    base: str
    kiosk: str  # the same store and station, served with the station file's page.kiosk
    browser: Any
    proc: StationProcess
    client: StationClient
    reader: Services
    token: str
    stopped: bool = False

    def stop_station(self) -> None:
        self.stopped = True
        self.proc.stop()

    def page(self, base: str | None = None, logged_in: bool = True) -> Any:
        context = self.browser.new_context(viewport=PANEL)
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        if logged_in:
            login(page, base or self.base, self.token)
        page.goto(f"{base or self.base}/line")
        return page

    def place_part(self, dx_mm: float) -> None:
        """The simulated part at its taught place, moved ``dx_mm`` along the robot's X."""
        station = self.proc.station
        T = station.active.config.T_rf_from_pf0.matrix.copy()
        T[0, 3] += dx_mm
        t = threading.Thread(target=lambda: station.scene.set_part_pose(T))
        t.start()
        t.join(30)

    def trigger(self, part_id: str) -> dict[str, Any]:
        out: list[dict[str, Any]] = []
        t = threading.Thread(target=lambda: out.append(
            self.client.trigger(part_id=part_id).model_dump(mode="json")))
        t.start()
        t.join(60)
        return out[0]


@pytest.fixture(scope="module")
def line(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Line]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("line")
    path = stations.station_file(tmp, "station1", stations.relaxed_deadline)
    cfg = stations.settings_for(path, tmp / "var")
    station = load_station(path)
    station = station.model_copy(update={"links": {
        **station.links, "modbus": {**station.links.get("modbus", {}), "host": "127.0.0.1",
                                    "port": 0}}})
    proc = StationProcess(cfg, station, stations.runtime_options())
    proc.start()
    reader = open_services(cfg, seed=False, bootstrap=False)
    site: Line | None = None
    try:
        token = create_token(reader.store.tokens, "line-read", Role.READ)[0]
        client = StationClient(cfg.resolved_control_socket)
        (tmp / "kiosk").mkdir()
        kiosk_file = stations.station_file(tmp / "kiosk", "station1", stations.relaxed_deadline,
                                           lambda data: data.update(page={"kiosk": True}))
        public = cfg.model_copy(update={"station": kiosk_file})
        with serve(create_app(cfg, client)) as base, \
                serve(create_app(public, StationClient(cfg.resolved_control_socket))) as kiosk, \
                sync_playwright() as pw:
            browser = launch(pw)
            site = Line(base, kiosk, browser, proc, client, reader, token)
            try:
                yield site
            finally:
                browser.close()
    finally:
        reader.close()
        if site is None or not site.stopped:
            proc.stop()


def _newest(page: Any, rec_id: int) -> None:
    page.wait_for_function(
        f"document.querySelector('#line-view').dataset.newest === '{rec_id}'", timeout=20000)


def _colour(page: Any, rgb: str) -> None:
    """The verdict tile's colour, once htmx has settled the swap: it sets the new class only
    then (its attributesToSettle), so the colour is waited for, not read at the swap."""
    page.wait_for_function(
        f"getComputedStyle(document.querySelector('#verdict')).backgroundColor === '{rgb}'",
        timeout=5000)


def _shot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"))
    print(f"screenshot: {SHOTS / name}.png")
    assert not page.errors, page.errors


def test_the_line_view_follows_the_line(line: Line) -> None:
    page = line.page()
    tile = page.locator("#verdict")
    assert tile.get_attribute("data-verdict") == "NONE" and "no result yet" in tile.inner_text()
    assert "waiting for the PLC" in page.locator("#station-state").inner_text()
    assert "modbus" in page.locator("#link-state").inner_text()
    assert page.locator(".streak").count() == 0
    assert_accessible(page, "/line, no result")

    # the part 150 mm off its place: NOKs (frames kept), three in a row (the recipe's
    # nok_streak_warning)
    line.place_part(150.0)
    noks = [line.trigger(f"VIN-N{k}") for k in range(3)]
    assert all(a["result_code"] != 0 for a in noks), noks
    _newest(page, noks[-1]["measurement_id"])
    assert tile.get_attribute("data-verdict") == "NOK"
    assert page.locator("#verdict .verdict-word").inner_text() == "NOK"
    _colour(page, "rgb(153, 27, 27)")
    streak = page.locator(".streak")
    assert streak.get_attribute("data-streak") == "3"
    code = line.reader.store.measurements.get(noks[-1]["measurement_id"]).record.reason_code
    assert "3 NOKs in a row" in streak.inner_text() and what_to_check(code) in streak.inner_text()

    # the strip: each NOK's frame, its reason in words and what to check
    items = page.locator("ul.noks li")
    assert items.count() == 3
    page.wait_for_function("[...document.querySelectorAll('ul.noks img')].length === 3 && "
                           "[...document.querySelectorAll('ul.noks img')].every("
                           "(i) => i.complete && i.naturalWidth > 0)", timeout=20000)
    first = items.first.inner_text()
    assert describe(code) in first and f"Check: {what_to_check(code)}" in first
    assert items.first.get_attribute("data-id") == str(noks[-1]["measurement_id"])
    assert_accessible(page, "/line, NOKs")
    _shot(page, "line-nok-1366x768")

    # the part at its taught place: OK, the warning goes
    line.place_part(0.0)
    ok = line.trigger("VIN-OK")
    assert ok["result_code"] == 0, ok
    _newest(page, ok["measurement_id"])
    assert page.locator("#verdict .verdict-word").inner_text() == "OK"
    _colour(page, "rgb(22, 101, 52)")
    assert page.locator(".streak").count() == 0

    # the shift's counts and cycle times are the store's
    window = shift_at(DEFAULT_SHIFTS, time_zone("UTC"), datetime.now(UTC))  # station1's
    counts = line.reader.store.shifts.counts(window.start, window.end)
    assert (counts.ok, counts.nok) == (1, 3)
    shown = {k: page.locator(f'.shift [data-count="{k}"]').inner_text()
             for k in ("ok", "nok", "yield", "min", "mean", "max")}
    assert shown == {"ok": "1", "nok": "3", "yield": "25.0 %",
                     "min": f"{counts.min_ms:.1f} ms", "mean": f"{counts.mean_ms:.1f} ms",
                     "max": f"{counts.max_ms:.1f} ms"}
    assert window.name in page.locator(".shift").inner_text()
    assert_accessible(page, "/line, OK")
    _shot(page, "line-ok-1366x768")
    page.context.close()


def test_the_verdict_reads_from_two_metres_on_the_panel(line: Line) -> None:
    """At 1366 x 768 on 15.6" (≈ 100 dpi, 3.9 px/mm) 9 mm letters need a cap height of ≈ 35 px:
    the rendered verdict's capitals are measured in the browser, in the font it drew them in."""
    line.place_part(0.0)
    ok = line.trigger("VIN-READ")  # a verdict of its own, whatever ran before
    assert ok["result_code"] == 0, ok
    page = line.page()
    _newest(page, ok["measurement_id"])
    # one script: the page swaps its view every few seconds (htmx), and an element looked up
    # in one call and measured in the next may be a detached one by then
    m = page.evaluate("""() => {
        const el = document.querySelector('#verdict .verdict-word');
        const ctx = document.createElement('canvas').getContext('2d');
        ctx.font = getComputedStyle(el).font;
        const t = ctx.measureText(el.textContent);
        const box = el.getBoundingClientRect();
        const tile = document.getElementById('verdict').getBoundingClientRect();
        return {word: el.textContent, cap: t.actualBoundingBoxAscent + t.actualBoundingBoxDescent,
                size: parseFloat(getComputedStyle(el).fontSize),
                height: box.height, bottom: tile.y + tile.height};
    }""")
    print(f"verdict: font-size {m['size']} px, capitals {m['cap']:.0f} px tall "
          f"(≈ {m['cap'] / 3.94:.0f} mm on the panel), line box {m['height']:.0f} px")
    assert m["word"] == "OK"
    assert m["cap"] >= MIN_CAP_PX
    assert m["height"] >= MIN_CAP_PX
    assert m["bottom"] <= PANEL["height"]  # on screen without scrolling
    page.context.close()


def test_a_kiosk_shows_the_line_view_and_nothing_else_without_a_login(line: Line) -> None:
    line.place_part(150.0)
    nok = line.trigger("VIN-KIOSK-NOK")  # a NOK of its own in the strip (its frames kept)
    assert nok["result_code"] != 0, nok
    line.place_part(0.0)
    page = line.page(line.kiosk, logged_in=False)
    assert page.url == f"{line.kiosk}/line"
    _newest(page, nok["measurement_id"])
    nok_id = page.locator("ul.noks li").first.get_attribute("data-id")
    assert nok_id == str(nok["measurement_id"])
    # its thumbnail comes with the view's next refresh after the archive wrote its frames
    page.wait_for_function("(() => { const i = document.querySelector("
                           "'ul.noks li:first-child img'); "
                           "return i !== null && i.complete && i.naturalWidth > 0; })()",
                           timeout=20000)
    assert page.locator("header nav a").count() == 0  # read-only: no tabs, no actions
    assert page.locator("button").count() == 0
    assert_accessible(page, "/line, kiosk")
    # it refreshes itself: a new result arrives without a reload
    page.evaluate("window.__same_page = 3")
    ok = line.trigger("VIN-KIOSK")
    _newest(page, ok["measurement_id"])
    assert page.evaluate("window.__same_page") == 3
    # everything else still needs a login
    page.goto(f"{line.kiosk}/history")
    assert page.url.startswith(f"{line.kiosk}/login")
    cam = line.reader.store.images.for_measurement(int(nok_id))[0]
    assert page.request.get(f"{line.kiosk}/web/frames/{nok_id}/1/{cam.camera_id}").status == 401
    assert page.request.get(
        f"{line.kiosk}/web/line/thumb/{nok_id}/1/{cam.camera_id}").status == 200
    ok_thumb = f"{line.kiosk}/web/line/thumb/{ok['measurement_id']}/1/{cam.camera_id}"
    assert page.request.get(ok_thumb).status == 404  # only NOKs' frames, never an OK's
    page.context.close()

    # without the setting the line view needs a login like every other page
    page = line.page(line.base, logged_in=False)
    assert page.url.startswith(f"{line.base}/login")
    assert page.request.get(f"{line.base}/web/line/fragment").status == 401
    page.context.close()


def test_a_station_that_goes_down_turns_the_tile_grey(line: Line) -> None:
    line.place_part(0.0)
    ok = line.trigger("VIN-DOWN")
    page = line.page()
    _newest(page, ok["measurement_id"])
    assert page.locator("#verdict").get_attribute("data-verdict") == "OK"
    line.stop_station()
    page.wait_for_function(
        "document.querySelector('#verdict').dataset.verdict === 'DOWN'", timeout=20000)
    _colour(page, "rgb(75, 85, 99)")
    assert page.locator("#verdict .verdict-word").inner_text() == "STATION DOWN"
    assert page.locator("#station-state").inner_text() == "station down"
    assert_accessible(page, "/line, station down")
    _shot(page, "line-down-1366x768")
    page.context.close()
