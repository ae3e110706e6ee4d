"""The live camera view (/cameras) in a real browser, beside a real station (simulated station 1).

The view shows each camera's frame and figures and updates; a trigger while it is open is
answered normally; once the page closes the station is asked for no more frames and grabs none;
the read role cannot open it; axe-core finds nothing serious. Screenshots go to var/screenshots/.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest
import stations
from axe import assert_accessible
from system_packages import ensure_commands
from waiting import until_sync

from mvpose_core.station import load_station
from server.app import create_app
from server.auth import Role, create_token
from server.state import Services, open_services
from server.station.camera_view import PERIOD_S
from server.station.client import StationClient
from server.station.process import StationProcess
from server.web.screenshots import VIEWPORT, launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"


@dataclass
class Site:
    base: str
    app: Any
    browser: Any
    proc: StationProcess
    client: StationClient
    tokens: dict[str, str]

    def page(self, role: str) -> Any:
        context = self.browser.new_context(viewport=VIEWPORT)
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        login(page, self.base, self.tokens[role])
        return page

    def trigger(self, part_id: str) -> dict[str, Any]:
        out: list[dict[str, Any]] = []
        t = threading.Thread(target=lambda: out.append(
            self.client.trigger(part_id=part_id).model_dump(mode="json")))
        t.start()
        t.join(60)
        return out[0]

    @property
    def counts(self) -> dict[str, int]:
        return dict(self.proc.station.camera_view.counts)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("cameras")
    path = stations.station_file(tmp, "station1", stations.relaxed_deadline)
    cfg = stations.settings_for(path, tmp / "var")
    station = load_station(path)
    station = station.model_copy(update={"links": {
        **station.links, "modbus": {**station.links.get("modbus", {}), "host": "127.0.0.1",
                                    "port": 0}}})
    proc = StationProcess(cfg, station,
                          replace(stations.runtime_options(), sim_part_at_reference=True))
    proc.start()
    reader: Services = open_services(cfg, seed=False, bootstrap=False)
    try:
        tokens = {role.value: create_token(reader.store.tokens, f"cam-{role.value}", role)[0]
                  for role in (Role.READ, Role.OPERATOR)}
        client = StationClient(cfg.resolved_control_socket)
        app = create_app(cfg, client)
        with serve(app) as base, sync_playwright() as pw:
            browser = launch(pw)
            try:
                yield Site(base, app, browser, proc, client, tokens)
            finally:
                browser.close()
    finally:
        reader.close()
        proc.stop()


def _seq(page: Any) -> int:
    return int(page.evaluate("document.getElementById('camera-view').dataset.seq || '0'"))


def test_the_view_shows_every_camera_updates_and_stops_when_closed(site: Site) -> None:
    cameras = [c.id for c in site.proc.station.station.cameras]
    assert site.counts["grabs"] == 0  # nobody has looked yet: nothing grabbed
    page = site.page("operator")
    page.goto(f"{site.base}/cameras")
    page.wait_for_function(
        f"""() => {{
            const figs = document.querySelectorAll('#camera-grid figure');
            return figs.length === {len(cameras)} && [...figs].every((f) =>
                f.querySelector('img').naturalWidth > 320 && f.dataset.focus !== '');
        }}""", timeout=30000)
    shown = page.eval_on_selector_all("#camera-grid figure", "fs => fs.map(f => f.dataset.camera)")
    assert shown == cameras
    for cid in cameras:
        fig = page.locator(f'#camera-grid figure[data-camera="{cid}"]')
        assert float(fig.get_attribute("data-focus") or 0) > 0
        text = fig.inner_text()
        assert "Focus" in text and "mark windows" in text and "saturated" in text

    first = _seq(page)
    page.wait_for_function(  # the view updates: a newer frame set arrives
        f"Number(document.getElementById('camera-view').dataset.seq) > {first}", timeout=30000)

    # a trigger while the view is open is answered normally, with its own result
    answer = site.trigger("VIN-CAM-1")
    assert answer["result_code"] == 0 and answer["final"], answer["message"]
    assert answer["record"] is not None and answer["offset"] is not None
    seen = _seq(page)
    page.wait_for_function(  # and the view goes on after it
        f"Number(document.getElementById('camera-view').dataset.seq) > {seen}", timeout=30000)

    assert_accessible(page, "camera view")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "cameras.png"), full_page=True)
    assert not page.errors, page.errors

    page.context.close()  # the last viewer leaves
    feed = site.app.state.web_cameras
    until_sync(lambda: not feed.running and feed.listeners == 0, "the feed stopped", 30.0)
    # an ask the feed sent before it stopped may still be on its way (its worker thread goes on;
    # one not yet sent is dropped and never sent): wait until the station has answered each one
    until_sync(lambda: feed.answered == feed.asks, "every ask sent answered", 30.0)
    asks = feed.asks
    assert site.counts["requests"] >= asks  # each of them reached the station
    after = site.counts
    # time passes with triggers on the line, longer than a few of the view's periods (a feed
    # still running would ask again within one); the station is asked nothing and grabs nothing
    start, k = time.monotonic(), 0
    while k < 3 or time.monotonic() - start < 3 * PERIOD_S:
        done = site.trigger(f"VIN-CAM-{k + 2}")
        assert done["result_code"] == 0, done["message"]
        k += 1
    assert site.counts == after
    assert feed.asks == asks


def test_the_read_role_cannot_open_the_view(site: Site) -> None:
    before = site.counts
    page = site.page("read")
    response = page.goto(f"{site.base}/cameras")
    assert response is not None and response.status == 403
    assert "operator" in page.inner_text("main")
    assert page.locator("#camera-view").count() == 0
    status = page.evaluate("fetch('/web/cameras/events').then((r) => r.status)")
    assert status == 403
    assert_accessible(page, "camera view refused")
    page.context.close()
    assert site.counts == before  # a refused viewer made the station grab nothing
