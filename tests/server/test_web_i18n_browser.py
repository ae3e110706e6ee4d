"""The operator page in each of its languages, in a real browser (Debian's Chromium driven by
Playwright): the line view and the history in English, German, Simplified Chinese and Spanish,
with the locale's numbers and dates in the plant's time zone; the language selector; the
script's messages (SPC, Live) in the chosen language; the Alarms and Cameras pages and the
hand-eye panel in German; axe-core on each.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo

import pytest
import stations
from axe import assert_accessible
from system_packages import ensure_commands
from waiting import until_sync

from server.app import create_app
from server.state import open_services
from server.store.schemas import StoredMeasurement
from server.web import i18n
from server.web.sample import SampleLine
from server.web.screenshots import VIEWPORT, launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
ZONE = "Europe/Berlin"

#: what each language shows: html lang, the verdict words, a heading of the line view and of
#: the history, the decimal separator, the date of 2 Nov 2026 as the locale writes it
WORDS = {
    "en": {"down": "STATION DOWN", "lang": "en", "ok": "OK", "nok": "NOK",
           "shift": "This shift", "check": "Check:", "history": "History", "point": ".",
           "date": r"[A-Z][a-z]{2} \d{1,2}, \d{4}"},
    "de": {"down": "STATION AUSGEFALLEN", "lang": "de", "ok": "i.O.", "nok": "n.i.O.",
           "shift": "Diese Schicht",
           "check": "Prüfen:", "history": "Verlauf", "point": ",",
           "date": r"\d{2}\.\d{2}\.\d{4}"},
    "zh_Hans": {"down": "工位停机", "lang": "zh-Hans", "ok": "合格", "nok": "不合格",
                "shift": "本班次",
                "check": "检查：", "history": "历史", "point": ".",
                "date": r"\d{4}年\d{1,2}月\d{1,2}日"},
    "es": {"down": "ESTACIÓN CAÍDA", "lang": "es", "ok": "OK", "nok": "NOK",
           "shift": "Este turno", "check": "Revisar:",
           "history": "Historial", "point": ",", "date": r"\d{1,2} [a-z]{3,5}\.? \d{4}"},
}


@dataclass
class Site:
    base: str
    browser: Any
    nok: StoredMeasurement  # the newest record: a NOK with frames
    app: Any

    def page(self, code: str | None = None, accept: str | None = None) -> Any:
        """A logged-in page; ``code`` as the selector's cookie, ``accept`` as the browser's
        Accept-Language."""
        context = self.browser.new_context(viewport=VIEWPORT, locale=accept or "en-US")
        if code is not None:
            context.add_cookies([{"name": i18n.COOKIE, "value": code, "url": self.base}])
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        login(page, self.base, stations.ENGINEER)
        return page


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("i18n")

    def plant(data: dict[str, Any]) -> None:
        data["time_zone"] = ZONE
        # one shift of 24 h that started 12 h ago: the records below are all in it
        start = datetime.now(ZoneInfo(ZONE)) - timedelta(hours=12)
        data["shifts"] = [{"name": "day", "start": f"{start:%H:%M}"}]

    cfg = stations.settings_for(stations.station_file(tmp, "station1", plant), tmp / "var")
    writer = open_services(cfg)
    try:
        line = SampleLine(writer, period_s=5.0)
        line.start = datetime.now(UTC) - timedelta(seconds=line.period_s * 12)
        line.run(9, missing_every=4)
        nok = line.store(*line.record(missing="B2", frames=True))
        writer.store.alarms.raise_("camera:left1", "CAMERA_DOWN", "high",
                                   "camera left1 is down: no frame", {"camera": "left1",
                                                                      "reason": "no frame"})
        app = create_app(cfg)
        with serve(app) as base, sync_playwright() as pw:
            browser = launch(pw)
            try:
                yield Site(base, browser, nok, app)
            finally:
                browser.close()
    finally:
        writer.close()


def _shot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)
    assert not page.errors, page.errors


@pytest.mark.parametrize("code", list(WORDS))
def test_the_line_view_and_the_history_in_each_language(site: Site, code: str) -> None:
    w = WORDS[code]
    page = site.page(code)
    local = site.nok.record.triggered_at.astimezone(ZoneInfo(ZONE))
    page.goto(f"{site.base}/line")
    assert page.get_attribute("html", "lang") == w["lang"]
    # no station process here: the tile says so, with the newest result's verdict
    assert page.locator("#verdict").get_attribute("data-verdict") == "DOWN"
    assert page.locator("#verdict .verdict-word").inner_text() == w["down"]
    assert page.locator("#verdict .tile-words").inner_text().endswith(
        f"#{site.nok.id} {w['nok']}")
    assert page.locator(".shift h2").inner_text() == w["shift"]
    assert page.locator(".shift dt").first.inner_text() == w["ok"]
    # the cycle time with the locale's decimal separator; the yield with it too
    mean = page.locator('.shift [data-count="mean"]').inner_text()
    assert re.fullmatch(r"\d+" + re.escape(w["point"]) + r"\d ms", mean), mean
    assert re.fullmatch(r"\d+" + re.escape(w["point"]) + r"\d %",
                        page.locator('.shift [data-count="yield"]').inner_text())
    # the newest NOK: its time in the plant's zone and the locale's date, its reason and what
    # to check in words of the language
    nok = page.locator(f'ul.noks li[data-id="{site.nok.id}"]')
    when = nok.locator(".when").inner_text()
    assert re.search(w["date"], when), when
    assert f"{local.hour}:{local:%M:%S}" in when and "CET" in when
    with i18n.use(code):
        reason = i18n.reason_words(site.nok.record.reason_code)
        check = i18n.check_words(site.nok.record.reason_code)
    assert reason in nok.inner_text() and f"{w['check']} {check}".replace("： ", "：") in (
        nok.inner_text().replace("： ", "："))
    assert_accessible(page, f"/line in {code}")
    _shot(page, f"i18n-line-{code}")

    page.goto(f"{site.base}/history?limit=8")
    assert page.get_attribute("html", "lang") == w["lang"]
    assert page.locator("main h2").first.inner_text() == w["history"]
    row = page.locator(f'#rows tr[data-id="{site.nok.id}"]')
    assert row.locator('td[data-result]').inner_text() == w["nok"]
    stamp = row.locator("time")
    assert re.search(w["date"], stamp.inner_text()) and f"{local.hour}:{local:%M:%S}" in (
        stamp.inner_text())
    assert stamp.get_attribute("datetime").startswith(
        site.nok.record.triggered_at.strftime("%Y-%m-%dT%H:%M:%S"))
    ok_row = page.locator("#rows tr.ok").first
    offsets = ok_row.locator("td").nth(7).inner_text().split()
    assert len(offsets) == 3 and all(
        re.fullmatch(r"−?-?\d+" + re.escape(w["point"]) + r"\d\d", v) for v in offsets), offsets
    assert_accessible(page, f"/history in {code}")
    _shot(page, f"i18n-history-{code}")
    page.context.close()


def test_the_browsers_language_then_the_selector(site: Site) -> None:
    # no choice yet: the browser's Accept-Language (Chromium sends its locale's)
    page = site.page(accept="es-ES")
    assert page.get_attribute("html", "lang") == "es"
    assert page.locator("header nav a.on").inner_text() == "En vivo"
    # the Live page's pushed fragments are rendered in the page's language
    page.wait_for_function("document.getElementById('live').dataset.connected === '1'")
    assert page.locator("#result h2").inner_text().startswith("Último resultado")
    # the user picks German: a cookie, the page again in German, and every page after it
    page.select_option("#lang-select", "de")
    page.wait_for_function("document.documentElement.lang === 'de'")
    assert page.locator("#result h2").inner_text().startswith("Letztes Ergebnis")
    assert {c["name"]: c["value"] for c in page.context.cookies()}[i18n.COOKIE] == "de"
    # one feed per language the page is open in, each rendering in its language
    feeds = site.app.state.web_live.feeds
    until_sync(lambda: feeds["de"].listeners == 1, "the German page listens to the German feed",
               15)
    page.goto(f"{site.base}/spc")
    page.wait_for_selector("#charts[data-points]")
    # the script's texts from the catalogue, its numbers with a decimal comma
    axis = page.evaluate("document.querySelector('#charts .chart').plot.axes[0].label")
    assert axis == f"Zeit ({ZONE})"
    labels = page.evaluate("document.querySelector('#charts .chart').plot.series"
                           ".map((s) => s.label)")
    assert {"OEG", "Mitte", "UEG", "Regel verletzt"} <= set(labels)
    capability = page.locator("#charts p.capability").first.inner_text()
    assert capability.startswith("Über die ") and re.search(r"Cp \d+,\d\d", capability)
    ticks = page.evaluate("[...document.querySelectorAll('#charts .chart')]"
                          ".flatMap((c) => c.plot.axes[1]._values || [])")
    assert any("," in v for v in ticks if v) and not any("." in v for v in ticks if v), ticks
    assert "Basis der Eingriffsgrenzen: die ersten 50 Punkte" in page.inner_text(
        "#charts .spc-head")
    assert_accessible(page, "/spc in de")
    # and back to English, the source
    page.select_option("#lang-select", "en")
    page.wait_for_function("document.documentElement.lang === 'en'")
    assert page.locator("main h2").first.inner_text() == "SPC"
    assert not page.errors, page.errors
    page.context.close()


def test_the_alarms_cameras_and_hand_eye_pages_in_german(site: Site) -> None:
    page = site.page("de")
    page.goto(f"{site.base}/alarms")
    assert page.get_attribute("html", "lang") == "de"
    assert page.locator("header nav a.on").inner_text() == "Alarme"
    assert page.locator("#standing-h").inner_text() == "Anstehende Alarme"
    # the alarm's text from its key and arguments, its priority and state in words
    row = page.locator('#standing-alarms tr[data-code="CAMERA_DOWN"]')
    assert "Kamera left1 ist ausgefallen: no frame" in row.inner_text()
    assert row.locator(".prio").text_content() == "hoch"  # CSS writes it in capitals
    assert row.locator(".alarm-state").text_content() == "aktiv"
    assert row.locator("button.ack").inner_text() == "Quittieren"
    # the header's count, loaded by htmx
    badge = page.locator("#alarm-count .alarm-badge")
    badge.wait_for()
    assert badge.inner_text() == "⚠ 1 aktiver Alarm (1 nicht quittiert)"
    assert_accessible(page, "/alarms in de")

    page.goto(f"{site.base}/cameras")
    assert page.locator("header nav a.on").inner_text() == "Kameras"
    assert page.locator(".camera-help h2").inner_text() == "Die Kennzahlen lesen"
    # no station process here: the script says so in German, from the page's catalogue
    page.wait_for_function(
        "document.getElementById('camera-note').textContent.startsWith('Keine Bilder:')")
    assert_accessible(page, "/cameras in de")

    # the Calibration page's hand-eye panel (no station process: it says so)
    page.goto(f"{site.base}/calibration")
    assert page.locator("#handeye h2").inner_text() == "Robotergeführte Hand-Auge-Kalibrierung"
    assert "Die Station ist ausgefallen: keine Sitzung anzuzeigen." in page.inner_text("#handeye")
    assert not page.errors, page.errors
    page.context.close()
