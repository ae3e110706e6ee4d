"""The Alarms page (/alarms) in a real browser (Playwright + Debian's Chromium) beside a real
station process (simulated station 1) whose Modbus link has no PLC yet: LINK_NO_PLC is raised
by the station's alarm watch, shown on the page, in the header's count and on the line view,
acknowledged by an operator (named), cleared when a PLC connects, and found in the history with
the filters. axe-core finds no serious or critical violation; screenshots go to
var/screenshots/."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import stations
from axe import assert_accessible
from system_packages import ensure_commands

from mvpose_core.station import load_station
from server.app import create_app
from server.auth import Role, create_token
from server.loopback import attach_twin, detach_twin
from server.state import Services, open_services
from server.station.alarms import AlarmWatchOptions
from server.station.client import StationClient
from server.station.process import StationProcess
from server.store.alarms import AlarmFilter
from server.web.screenshots import launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
SIZES = {"1366x768": {"width": 1366, "height": 768}, "1920x1080": {"width": 1920, "height": 1080}}


@dataclass
class Site:
    base: str
    browser: Any
    proc: StationProcess
    reader: Services
    tokens: dict[str, str]

    def page(self, role: str, size: str = "1366x768") -> Any:
        page = self.browser.new_context(viewport=SIZES[size]).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        login(page, self.base, self.tokens[role])
        return page


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("alarms")
    path = stations.station_file(tmp, "station1", stations.relaxed_deadline)
    cfg = stations.settings_for(path, tmp / "var")
    station = load_station(path)
    station = station.model_copy(update={"links": {
        **station.links, "modbus": {**station.links.get("modbus", {}), "host": "127.0.0.1",
                                    "port": 0}}})
    proc = StationProcess(cfg, station, stations.runtime_options(),
                          AlarmWatchOptions(period_s=0.2, on_delay_s=0.5))
    proc.start()
    reader = open_services(cfg, seed=False, bootstrap=False)
    try:
        tokens = {role.value: create_token(reader.store.tokens, f"shift-{role.value}", role)[0]
                  for role in (Role.READ, Role.OPERATOR)}
        with serve(create_app(cfg, StationClient(cfg.resolved_control_socket))) as base, \
                sync_playwright() as pw:
            browser = launch(pw)
            try:
                yield Site(base, browser, proc, reader, tokens)
            finally:
                browser.close()
    finally:
        reader.close()
        proc.stop()


def _shot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)
    assert not page.errors, page.errors


def _row(page: Any, table: str) -> Any:
    return page.locator(f"#{table}-alarms tr[data-code=LINK_NO_PLC]")


def _reload_until(page: Any, url: str, check: str, what: str, timeout_s: float = 20) -> None:
    """Load ``url`` again until the JS expression ``check`` holds (the page does not poll)."""
    for _ in range(int(timeout_s / 0.25)):
        page.goto(url)
        if page.evaluate(check):
            return
        page.wait_for_timeout(250)
    raise AssertionError(f"{what}: not within {timeout_s:g} s")


class _Plc:
    """The line's PLC (the Modbus twin with its heartbeat) on a loop of its own."""

    def __init__(self, port: int) -> None:
        self.done = threading.Event()
        self.attached = threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run(port)), daemon=True)
        self.thread.start()
        assert self.attached.wait(30), "the PLC twin did not connect"

    async def _run(self, port: int) -> None:
        twin, beat = await attach_twin(port, poll_s=0.01)
        self.attached.set()
        try:
            while not self.done.is_set():
                await asyncio.sleep(0.05)
        finally:
            await detach_twin(twin, beat)

    def close(self) -> None:
        self.done.set()
        self.thread.join(10)


def test_raise_shown_acknowledged_cleared_and_in_history(site: Site) -> None:
    url = f"{site.base}/alarms"
    page = site.page("operator")
    # raised by the station's alarm watch: the link has no PLC heartbeat
    _reload_until(page, url, "!!document.querySelector('#standing-alarms "
                  "tr[data-code=LINK_NO_PLC]')", "LINK_NO_PLC on the page")
    row = _row(page, "standing")
    assert "link modbus: no PLC heartbeat" in row.inner_text()
    assert row.locator("td.alarm-state").inner_text() == "active"
    assert row.locator("td.prio").inner_text().lower() == "high"
    badge = page.locator("#alarm-count .alarm-badge")
    badge.wait_for(timeout=10000)
    assert badge.inner_text() == "⚠ 1 active alarm (1 unacknowledged)"
    assert_accessible(page, "/alarms, one active alarm")
    for size in SIZES:
        shot = site.page("operator", size)
        shot.goto(url)
        shot.locator("#alarm-count .alarm-badge").wait_for(timeout=10000)
        _shot(shot, f"alarms-{size}")
        shot.context.close()

    # the line view shows it in words
    page.goto(f"{site.base}/line")
    banner = page.locator("#alarm-banner")
    assert banner.get_attribute("data-active") == "1"
    assert "no PLC heartbeat" in banner.inner_text()

    # a read token sees it and may not acknowledge
    reader = site.page("read")
    reader.goto(url)
    assert _row(reader, "standing").locator("td.ack").inner_text() == "not yet"
    assert reader.locator("button.ack").count() == 0
    reader.context.close()

    # the operator acknowledges it: named, with the time
    page.goto(url)
    _row(page, "standing").locator("button.ack").click()
    page.wait_for_function("document.querySelector('#standing-alarms tr[data-code=LINK_NO_PLC]')"
                           "?.classList.contains('acked')", timeout=20000)
    assert _row(page, "standing").locator("td.ack").inner_text().startswith("shift-operator, ")
    alarm = site.reader.store.alarms.find(AlarmFilter(source="link:modbus"))[0]
    assert alarm.acked_by == "shift-operator"

    # a PLC connects: the alarm clears; acknowledged and cleared, it leaves the standing list
    plc = _Plc(site.proc.station.link_port("modbus"))
    try:
        _reload_until(page, url, "!document.querySelector('#standing-alarms "
                      "tr[data-code=LINK_NO_PLC]')", "LINK_NO_PLC cleared")
    finally:
        plc.close()
    assert page.locator("#standing-empty").inner_text() == "No alarms."

    # the history, filtered: cleared and acknowledged alarms of the links
    page.select_option("#f-state", "cleared")
    page.select_option("#f-acknowledged", "yes")
    page.fill("#f-source", "link:")
    page.click("#alarm-filters button[type=submit]")
    page.wait_for_url("**/alarms?*")
    hist = _row(page, "history")
    assert hist.locator("td.alarm-state").inner_text() == "cleared"
    assert hist.locator("td.ack").inner_text().startswith("shift-operator, ")
    page.select_option("#f-state", "active")
    page.click("#alarm-filters button[type=submit]")
    page.wait_for_url("**state=active*")
    assert _row(page, "history").count() == 0
    assert_accessible(page, "/alarms, history filtered")

    # a mistyped time is said on the page (no 400, no blank page)
    page.goto(f"{url}?since=yesterday")
    assert "since: 'yesterday' is not a date" in page.locator(".form-errors").inner_text()
    assert_accessible(page, "/alarms, a filter error")
    _shot(page, "alarms-filter-error-1366x768")
    page.context.close()
