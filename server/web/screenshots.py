"""Screenshots of every page of the operator page, for docs/operator-page.md (and the browser tests'
helpers: the app on a real socket, Debian's Chromium through Playwright).

    python -m server.web.screenshots --out docs/figures

starts the API app on a temporary SQLite store, fills it with records the pose engine measured
on simulated station 1 (server.web.sample), ending now, starts a station process on it (simulated
cameras, no PLC: its link's alarm is the active one on Alarms), logs in and saves every page
as the screen shows it, at a full-HD monitor's 1920 x 1080 and the panel PC's 1366 x 768, in
English and German (the selector's cookie):
``operator-<page>-<language>-<w>x<h>.jpg``, JPEG quality 70. Needs the ``test`` extra
(playwright) and /usr/bin/chromium (Debian's ``chromium``).
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import uvicorn
from fastapi import FastAPI

from server.settings import Settings
from server.state import Services, open_services
from server.store.schemas import MeasurementFilter
from server.web.sample import SampleLine

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run"]
STATION1 = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"
VIEWPORT = {"width": 1440, "height": 900}
#: the screens: a full-HD monitor and the panel PC's (15.6", 1366 x 768)
SCREENS = ({"width": 1920, "height": 1080}, {"width": 1366, "height": 768})
#: the languages of the pictures in the docs (the page has four: server/web/i18n.py)
SHOWN = ("en", "de")
QUALITY = 70
#: each page: its path (``{record}``: a NOK with frames) and what shows that it is drawn
PAGES = {
    "login": ("/login", "#login-form"),
    "live": ("/", "#frames figure.cam img"),
    "line": ("/line", "ul.noks img"),
    "history": ("/history?limit=30", "table.history"),
    "record": ("/history/{record}", "figure.cam img"),
    "spc": ("/spc", "#charts[data-points]"),
    "calibration": ("/calibration", "#charts[data-points]"),
    "recipes": ("/recipes/floor_panel", "table.diff"),
    "gauge": ("/gauge", "main section"),
    "alarms": ("/alarms", '#standing-alarms tr[data-state="active"]'),
    "cameras": ("/cameras", "#camera-grid figure img[src]"),
    "docs": ("/docs", ".swagger-ui .opblock"),  # Swagger UI's own words: English only
}


@contextmanager
def serve(app: FastAPI) -> Iterator[str]:
    """The app under uvicorn on 127.0.0.1, a free port, its own thread; yields the base URL."""
    config = uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning",
                            timeout_graceful_shutdown=2)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="web-uvicorn", daemon=True)
    thread.start()
    started = threading.Event()
    while not started.wait(0.02):  # uvicorn has no start callback: watch its flag
        if server.started:
            started.set()
        elif not thread.is_alive():
            raise RuntimeError("uvicorn did not start the operator page's app")
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)


def launch(playwright: Any) -> Any:
    """Debian's Chromium (never a downloaded browser), headless."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)


def login(page: Any, base: str, token: str) -> None:
    """Log in with an API token (the login page's "with an API token" part)."""
    page.goto(f"{base}/login")
    page.click("#token-login summary")
    page.fill("input[name=token]", token)
    page.click("#token-form button[type=submit]")
    page.wait_for_url(f"{base}/")


def login_user(page: Any, base: str, user: str, secret: str) -> None:
    """Log in with a user's name and PIN or password; waits for the Live page."""
    page.goto(f"{base}/login")
    page.fill("input[name=user]", user)
    page.fill("input[name=secret]", secret)
    page.click("#login-form button[type=submit]")
    page.wait_for_url(f"{base}/")


def populate(services: Services, plain: int = 560, moved: int = 120,
             end: datetime | None = None) -> SampleLine:
    """A morning of production: ``plain`` results (some NOK; enough for the drift watch to learn
    the noise), then ``moved`` results after camera back_right moved by (0.4, -0.2) px, two
    results with frames kept, and a taught recipe version that is not active yet; the last
    result at ``end`` when given."""
    line = SampleLine(services, period_s=20.0)
    if end is not None:
        line.start = end - timedelta(seconds=line.period_s * (plain + moved + 9))
    line.run(plain, missing_every=37)
    line.run(moved, shift_px=(0.4, -0.2), shift_camera="back_right")
    line.store(*line.record(missing="B2", frames=True))
    line.run(5)
    taught = line.store(*line.record(frames=True))
    line.run(2)
    line.taught_version(taught)
    return line


def main(argv: list[str] | None = None) -> int:
    from playwright.sync_api import sync_playwright

    from mvpose_core.station import load_station
    from server.app import create_app
    from server.station.client import StationClient
    from server.station.options import StationOptions
    from server.station.process import StationProcess

    parser = argparse.ArgumentParser(prog="python -m server.web.screenshots",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    parser.add_argument("--languages", default=",".join(SHOWN),
                        help="comma-separated: en, de, zh_Hans, es (default: %(default)s)")
    args = parser.parse_args(argv)
    languages = [c.strip() for c in args.languages.split(",") if c.strip()]
    args.out.mkdir(parents=True, exist_ok=True)
    token = "mvp_screenshots-engineer-0123456789"
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), station=STATION1, bootstrap_token=token,
                            sqlite_synchronous="NORMAL")
        writer = open_services(settings)  # the station process's side: it writes the records
        station = load_station(STATION1)
        modbus = {**station.links.get("modbus", {}), "host": "127.0.0.1", "port": 0}
        # the simulated part lies at the recipe's reference: the Cameras page sees it
        proc = StationProcess(settings, station.model_copy(update={
            "links": {**station.links, "modbus": modbus}}),
            StationOptions(sim_part_at_reference=True))
        try:
            line = populate(writer, end=datetime.now(UTC) - timedelta(seconds=20))
            newest = writer.store.measurements.summary_page(MeasurementFilter(), None, 1)[0]
            line.store(*line.record(missing="B2", frames=True))  # Live and Line show a NOK
            proc.start()
            # no PLC on the link: the station's alarm watch raises LINK_NO_PLC after its
            # on-delay, the active alarm the Alarms page shows
            standing(writer, timeout_s=120)
            app = create_app(settings, StationClient(settings.resolved_control_socket))
            with serve(app) as base, sync_playwright() as pw:
                browser = launch(pw)
                record = newest[0].id - 2  # the OK with frames populate() taught from
                for code in languages:
                    for size in SCREENS:
                        shoot(browser, base, token, code, size, record, args.out)
                browser.close()
        finally:
            proc.stop()
            writer.close()
    return 0


def standing(services: Services, timeout_s: float) -> None:
    """Wait for an active alarm in the store (the station's watch writes it)."""
    end = time.monotonic() + timeout_s
    while not any(a.active for a in services.store.alarms.standing()):
        if time.monotonic() > end:
            raise RuntimeError(f"no active alarm within {timeout_s:g} s for the Alarms page")
        time.sleep(0.5)


def shoot(browser: Any, base: str, token: str, code: str, size: dict[str, int], record: int,
          out: Path) -> None:
    """Every page in language ``code`` on a screen of ``size``."""
    from server.web.i18n import COOKIE

    context = browser.new_context(viewport=size)
    context.add_cookies([{"name": COOKIE, "value": code, "url": base}])
    page = context.new_page()
    page.on("pageerror", lambda err: print(f"page error: {err}"))
    for name, (path, ready) in PAGES.items():
        if name == "docs" and code != "en":
            continue
        if name == "live":
            login(page, base, token)
        page.goto(base + path.format(record=record))
        page.wait_for_selector(ready)
        page.wait_for_function(  # images drawn; the drift watch answers after the page
            "[...document.images].every((i) => i.complete && i.naturalWidth > 0) && "
            "!document.querySelector('#drift[data-loading]')", timeout=60000)
        target = out / f"operator-{name}-{code}-{size['width']}x{size['height']}.jpg"
        page.screenshot(path=str(target), type="jpeg", quality=QUALITY)
        print(target)
    context.close()


if __name__ == "__main__":
    raise SystemExit(main())
