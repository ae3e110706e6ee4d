"""The operator page in a real browser: Debian's Chromium driven by Playwright.

One API app on a real socket (port 0) reads a SQLite store that a second set of services writes
into, as the station process does; the records are the pose engine's own on simulated station 1
(server.web.sample). Screenshots of every page go to var/screenshots/ (printed).
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from apps import ENGINEER, settings
from axe import assert_accessible
from system_packages import ensure_commands
from waiting import until_sync

from mvpose_core.offset import frame_offsets
from mvpose_core.reasons import Reason
from mvpose_core.shifts import DEFAULT_SHIFTS, shift_at, time_zone
from server.app import create_app
from server.auth import Role, create_token
from server.state import Services, open_services
from server.store.schemas import MeasurementRecord, Offset, StoredMeasurement
from server.web.geometry import recipe_from_content
from server.web.sample import SampleLine
from server.web.screenshots import VIEWPORT, launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
BULK = 1200  # results on the SPC charts besides the sample line's (22 charts: ~27,000 points)


@dataclass
class Site:
    base: str
    browser: Any
    writer: Services  # the station process's side of the store
    line: SampleLine
    tokens: dict[str, str]
    framed: StoredMeasurement  # newest record with frames when the tests start
    ok_framed: StoredMeasurement
    app: Any

    def page(self, role: str = "engineer") -> Any:
        context = self.browser.new_context(viewport=VIEWPORT)
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        login(page, self.base, self.tokens[role])
        return page

    def shot(self, page: Any, name: str, full_page: bool = True) -> None:
        SHOTS.mkdir(parents=True, exist_ok=True)
        path = SHOTS / f"{name}.png"
        page.screenshot(path=str(path), full_page=full_page)
        print(f"screenshot: {path}")
        assert not page.errors, page.errors


def _bulk(line: SampleLine, n: int) -> None:
    """``n`` results fast: one measured record replayed with new numbers (SPC charts)."""
    rng = np.random.default_rng(3)
    template, _ = line.record()
    assert template.offset is not None and template.uncertainty is not None
    for _ in range(n):
        line.trigger_id += 1
        off = [v + float(rng.normal(0, 0.5)) for v in template.offset.values]
        line.services.record_measurement(template.model_copy(update={
            "trigger_id": line.trigger_id, "part_id": f"VIN{line.trigger_id:06d}",
            "triggered_at": line.start + timedelta(seconds=line.period_s * line.trigger_id),
            "offset": Offset(convention=template.offset.convention, values=off),
            "timings_ms": {**template.timings_ms, "total": float(rng.uniform(15, 35))},
        }))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    cfg = settings(tmp_path_factory.mktemp("web"), sqlite_synchronous="NORMAL")
    writer = open_services(cfg)
    try:
        line = SampleLine(writer)
        _bulk(line, BULK)
        line.run(12, missing_every=4)
        ok_framed = line.store(*line.record(frames=True))
        line.run(3)
        framed = line.store(*line.record(missing="B2", frames=True))
        line.run(2)
        line.taught_version(ok_framed)
        tokens = {"engineer": ENGINEER}
        for role in (Role.READ, Role.OPERATOR):
            tokens[role.value] = create_token(writer.store.tokens, f"b-{role.value}", role)[0]
        app = create_app(cfg)
        with serve(app) as base, sync_playwright() as pw:
            browser = launch(pw)
            try:
                yield Site(base, browser, writer, line, tokens, framed, ok_framed, app)
            finally:
                browser.close()
    finally:
        writer.close()


def _in_thread(fn: Any) -> Any:
    """Run a store write off the test's thread (the station writes from its own process)."""
    out: list[Any] = []
    t = threading.Thread(target=lambda: out.append(fn()))
    t.start()
    t.join(60)
    return out[0]


def _overlay_points(page: Any, figure: Any) -> list[dict[str, float]]:
    """Each found-mark circle's centre on screen, scaled back to full-resolution pixels."""
    return figure.evaluate("""(fig) => {
        const img = fig.querySelector('img').getBoundingClientRect();
        const W = Number(fig.dataset.width), H = Number(fig.dataset.height);
        return [...fig.querySelectorAll('circle.found')].map((c) => {
            const r = c.getBoundingClientRect();
            return {mark: c.dataset.mark,
                    u: (r.left + r.width / 2 - img.left) * W / img.width,
                    v: (r.top + r.height / 2 - img.top) * H / img.height};
        });
    }""")


def _check_overlays(site: Site, page: Any, stored: StoredMeasurement) -> None:
    """Each found-mark circle sits on the record's detection, on a dark disc of its image."""
    detected = {(cd.camera_id, d.mark_id): d.uv for cd in stored.record.detections
                for d in cd.detections if d.found}
    checked = 0
    for figure in page.locator("figure.cam").element_handles():
        cam = figure.get_attribute("data-camera")
        image = None
        for ref in stored.record.images:
            if ref.camera_id == cam:
                image = cv2.imread(str(site.writer.images.resolve(ref.path)), 0)
        assert image is not None
        for p in _overlay_points(page, figure):
            uv = detected[(cam, p["mark"])]
            assert math.hypot(p["u"] - uv[0], p["v"] - uv[1]) < 2.0, (cam, p, uv)
            # and the mark really is there: a dark disc under the circle, light around it
            u, v = round(uv[0]), round(uv[1])
            inner = image[v - 3:v + 4, u - 3:u + 4].mean()
            ring = np.r_[image[v - 20, u - 20:u + 21], image[v + 20, u - 20:u + 21]].mean()
            assert inner < ring - 40, (cam, p["mark"], inner, ring)
            checked += 1
        assert figure.query_selector_all("rect.window")
    assert checked == 7


def _all_frames_loaded(page: Any, n: int) -> None:
    page.wait_for_function(
        f"(() => {{ const i = [...document.querySelectorAll('#frames img')]; return i.length "
        f"=== {n} && i.every((x) => x.complete && x.naturalWidth > 0); }})()", timeout=20000)


def test_live_overlays_sit_on_the_marks_and_results_arrive_without_reload(site: Site) -> None:
    page = site.page("engineer")
    newest = site.framed.id + 2  # two results after the framed NOK kept no frames
    frames = page.locator("#frames")
    assert page.locator("#result").get_attribute("data-id") == str(newest)
    # the images panel is the newest result's (its marks on grey), with a link to the NOK
    assert frames.get_attribute("data-id") == str(newest)
    assert page.locator("#frames img").count() == 0
    assert frames.locator(f'a[href="/history/{site.framed.id}"]').count() == 1
    assert page.locator("#status .state").inner_text() == "station down"

    # A new result is pushed (server-sent events): the page shows it without reloading. A
    # second browser gets it from the same single watcher of the store.
    other = site.page("read")
    other.wait_for_function("document.getElementById('live').dataset.connected === '1'")
    feeds = site.app.state.web_live  # one feed per language; both pages read English
    feed = feeds.of("en")
    # the browser says it is connected when its stream opened; the server counts it as it
    # starts serving that stream, which a busy machine may do a moment later
    until_sync(lambda: feed.listeners == 2, "both pages listen to the one feed", 15)
    page.evaluate("window.__same_page = 42")
    new = _in_thread(lambda: site.line.store(*site.line.record()))
    for p in (page, other):
        p.wait_for_function(f"document.querySelector('#result').dataset.id === '{new.id}'",
                            timeout=15000)
    assert page.evaluate("window.__same_page") == 42
    until_sync(lambda: feed.listeners == 2, "both pages still listen", 15)
    assert feed.running and list(feeds.feeds) == ["en"]  # one watcher for both
    other.context.close()
    framed = _in_thread(lambda: site.line.store(*site.line.record(missing="B2", frames=True)))
    page.wait_for_function(f"document.querySelector('#frames').dataset.id === '{framed.id}'",
                           timeout=15000)
    _all_frames_loaded(page, 4)
    _check_overlays(site, page, framed)
    assert page.locator('#frames g.missing[data-mark="B2"]').count() == 1
    assert "marks the recipe needs were not found" in page.locator("#result").inner_text()
    assert page.evaluate("window.__same_page") == 42
    site.shot(page, "live")
    page.context.close()


def test_live_shows_every_frame_of_a_nok_once_the_archive_has_written_it(site: Site) -> None:
    """The archive writes a record's frames one camera after another, after the record: the
    Live page waits for the last one (it showed 'frame not archived' for the rest)."""
    page = site.page("read")
    page.wait_for_function("document.getElementById('live').dataset.connected === '1'")
    record, images = site.line.record(missing="B2", frames=True)
    archive = site.writer.images
    refs = archive.plan(record.station, record.trigger_id, record.triggered_at, False,
                        sorted(images))
    stored = _in_thread(lambda: site.writer.record_measurement(
        record.model_copy(update={"images": refs})))
    _in_thread(lambda: archive.write(stored.id, refs[:2], False, images))
    page.wait_for_function(f"document.querySelector('#frames').dataset.id === '{stored.id}'",
                           timeout=15000)
    _in_thread(lambda: archive.write(stored.id, refs[2:], False, images))
    _all_frames_loaded(page, 4)
    assert page.locator("#frames .noframe").count() == 0
    page.context.close()


def test_live_never_puts_an_older_records_images_beside_a_newer_result(site: Site) -> None:
    page = site.page("read")
    page.wait_for_function("document.getElementById('live').dataset.connected === '1'")
    nok = _in_thread(lambda: site.line.store(*site.line.record(missing="B2", frames=True)))
    page.wait_for_function(f"document.querySelector('#frames').dataset.id === '{nok.id}'",
                           timeout=15000)
    _all_frames_loaded(page, 4)
    ok = _in_thread(lambda: site.line.store(*site.line.record()))
    page.wait_for_function(f"document.querySelector('#result').dataset.id === '{ok.id}'",
                           timeout=15000)
    page.wait_for_function(f"document.querySelector('#frames').dataset.id === '{ok.id}'",
                           timeout=15000)
    frames = page.locator("#frames")
    assert page.locator("#frames img").count() == 0  # the NOK's images are gone
    assert f"({ok.record.result})" in frames.locator("h2").inner_text()
    assert frames.locator(f'a[href="/history/{nok.id}"]').count() == 1  # linked, in words
    assert "kept no frames" in frames.inner_text()
    page.context.close()


def test_a_noks_measured_offset_says_it_was_not_sent(site: Site) -> None:
    template, _ = site.line.record()
    assert template.offset is not None
    nok = template.model_copy(update={
        **MeasurementRecord.reason_fields(Reason.OFFSET_TRANSLATION_OUT_OF_RANGE),
        "message": "offset 140 mm > 100 mm"})
    stored = _in_thread(lambda: site.line.store(nok, {}))
    page = site.page("read")
    page.wait_for_function(f"document.querySelector('#result').dataset.id === '{stored.id}'",
                           timeout=15000)
    for where in (f"{site.base}/", f"{site.base}/history/{stored.id}"):
        page.goto(where)
        table = page.locator("#result table.offset")
        assert table.get_attribute("data-sent") == "false"
        assert "NOT SENT to the robot" in table.locator("caption").inner_text()
        # one script, so the live feed's swap of #result cannot detach the cell between its
        # look-up and its style (a detached element's computed style is empty)
        assert page.evaluate("getComputedStyle(document.querySelector("
                             "'#result table.offset td')).textDecorationLine") == "line-through"
    # an OK's offset looks like what it is: sent
    ok = _in_thread(lambda: site.line.store(*site.line.record()))
    page.goto(f"{site.base}/history/{ok.id}")
    assert page.locator("#result table.offset").get_attribute("data-sent") == "true"
    assert "NOT SENT" not in page.locator("#result").inner_text()
    page.context.close()


def test_live_counts_the_shift_from_the_store(site: Site) -> None:
    """The Live page's counts are the store's, for the current shift: a restarted station
    process (or API process) does not start them at 0."""
    page = site.page("read")
    page.wait_for_function("document.getElementById('live').dataset.connected === '1'")
    window = shift_at(DEFAULT_SHIFTS, time_zone("UTC"), datetime.now(UTC))
    counts = site.writer.store.shifts.counts(window.start, window.end)
    assert page.locator('#status [data-count="ok"]').inner_text() == str(counts.ok)
    assert page.locator('#status [data-count="nok"]').inner_text() == str(counts.nok)
    assert window.name in page.locator("#status .counts").inner_text()
    record, _ = site.line.record(missing="B2")
    now = datetime.now(UTC)
    _in_thread(lambda: site.line.store(record.model_copy(update={"triggered_at": now}), {}))
    page.wait_for_function("document.querySelector('#status [data-count=\"nok\"]')"
                           f".textContent === '{counts.nok + 1}'", timeout=15000)
    assert page.locator('#status [data-count="ok"]').inner_text() == str(counts.ok)
    page.context.close()


def test_history_filters_paging_drill_down_and_export(site: Site) -> None:
    page = site.page("read")
    page.goto(f"{site.base}/history")
    page.select_option("#filters select[name=result]", "NOK")
    page.fill("#filters input[name=limit]", "3")
    page.click("#filters button[type=submit]")
    page.wait_for_function("location.search.includes('result=NOK')")
    rows = page.locator("#rows tbody tr")
    assert rows.count() == 3 and all(c == "nok" for c in
                                     rows.evaluate_all("(rs) => rs.map((r) => r.className)"))
    for _ in range(2):  # each next page replaces the list: one #rows, never one inside another
        if page.locator("#rows a.more").count() == 0:
            break
        first = page.locator("#rows tbody tr").first.get_attribute("data-id")
        page.click("#rows a.more")
        page.wait_for_function(f"!document.querySelector('#rows tr[data-id=\"{first}\"]')")
        assert page.evaluate("document.querySelectorAll('[id=rows]').length") == 1
        assert page.locator("#rows tbody tr.nok").count() >= 1
    site.shot(page, "history")
    href = page.locator("p.export a", has_text="CSV").get_attribute("href")
    csv = page.request.get(site.base + href)
    assert csv.ok and csv.headers["content-type"].startswith("text/csv")
    lines = csv.text().strip().splitlines()
    assert len(lines) > 4 and all(",NOK," in row for row in lines[1:])

    page.goto(f"{site.base}/history/{site.framed.id}")
    page.wait_for_function("[...document.querySelectorAll('figure.cam img')].every("
                           "(i) => i.complete && i.naturalWidth > 0)")
    text = page.inner_text("main")
    for words in ("Detections and residuals", "Timings", "floor_panel", "MARKS_MISSING",
                  site.framed.hash, "total"):
        assert words in text, words
    assert page.locator("line.residual").count() == 7
    assert page.locator("text=Teach this").count() == 0  # a read token does not teach
    site.shot(page, "record")
    page.context.close()


def test_history_says_why_a_mistyped_time_is_refused(site: Site) -> None:
    page = site.page("read")
    page.goto(f"{site.base}/history")
    page.fill("#filters input[name=since]", "yesterday 6 am")
    page.click("#filters button[type=submit]")
    alert = page.locator("#rows [role=alert]")
    alert.wait_for(timeout=10000)
    assert "since = 'yesterday 6 am' is not an ISO 8601 time" in alert.inner_text()
    page.fill("#filters input[name=since]", "2026-11-02T06:00")
    page.click("#filters button[type=submit]")
    page.wait_for_function("document.querySelector('#rows [role=alert]') && document"
                           ".querySelector('#rows [role=alert]').textContent.includes('no time "
                           "zone')")
    # a correct time filters again
    page.fill("#filters input[name=since]", "2026-11-02T06:00Z")
    page.click("#filters button[type=submit]")
    page.wait_for_selector("#rows table.history")
    assert page.locator("#rows [role=alert]").count() == 0
    # without htmx (a typed URL) the whole page says it too, with the 400
    answer = page.goto(f"{site.base}/history?until=later")
    assert answer is not None and answer.status == 400
    assert "until = 'later' is not an ISO 8601 time" in page.locator("[role=alert]").inner_text()
    page.context.close()


_TICKS = """() => [...document.querySelectorAll('#charts .chart')].map((c) => ({
    title: c.querySelector('h3').textContent,
    span: c.plot.scales.x.max - c.plot.scales.x.min,
    x: c.plot.axes[0]._values, y: c.plot.axes[1]._values,
    log: c.plot.scales.y.distr === 3}))"""


def _assert_readable_ticks(charts: list[dict[str, Any]], points: int, data_span: float) -> None:
    """Every chart: a time axis about as long as the data, tick labels that differ, no "−0",
    no time label cut to ":53.900"."""
    assert charts
    for c in charts:
        what = f"{c['title']} ({points} points)"
        assert c["span"] <= max(1.2 * data_span, 3600), (what, c["span"])  # not 1000 days
        for axis in ("x", "y"):
            ticks = [v for v in c[axis] if v]
            assert len(ticks) >= 2, (what, axis, c[axis])
            assert len(set(ticks)) == len(ticks), (what, axis, ticks)  # no label twice
            for v in ticks:
                assert not re.fullmatch(r"[-−]0(\.0*)?", v), (what, axis, ticks)
                assert not v.startswith(":"), (what, axis, ticks)


def test_chart_axes_are_readable_at_few_and_many_points(site: Site) -> None:
    page = site.page("read")
    page.goto(f"{site.base}/spc")
    for limit in (3, 60, 20000):
        page.fill("#trend-filters input[name=limit]", str(limit))
        page.click("#trend-filters button[type=submit]")
        page.wait_for_function(f"(() => {{ const c = document.querySelector('#charts'); "
                               f"return c.dataset.points && c.dataset.limit === '{limit}'; }})()",
                               timeout=60000)
        points = int(page.locator("#charts").get_attribute("data-points"))
        cols = page.request.get(f"{site.base}/web/trends.json?limit={limit}").json()["columns"]
        span = cols["t"][-1] - cols["t"][0]
        _assert_readable_ticks(page.evaluate(_TICKS), points, span)
    # the page's own chart() on made-up series up to 100,000 points (more than the store above
    # holds): a walk, a flat line near zero and a flat 100 %, 30 s apart
    for n in (3, 1000, 100_000):
        page.evaluate("""(n) => {
            const host = document.getElementById('charts');
            host.textContent = '';
            const x = [], walk = [], zero = [], full = [];
            let v = 0;
            for (let i = 0; i < n; i++) {
                x.push(1793772000 + 30 * i);
                v += Math.sin(i * 12.9898) * 0.01;
                walk.push(v); zero.push(-1e-17); full.push(100);
            }
            chart(host, 'walk', x, [{label: 'W', values: walk}], {unit: '°'});
            chart(host, 'zero', x, [{label: 'P', values: zero}], {unit: '°'});
            chart(host, 'full', x, [{label: 'NOK %', values: full}], {unit: '%'});
        }""", n)
        _assert_readable_ticks(page.evaluate(_TICKS), n, 30.0 * (n - 1))
    page.context.close()


def test_spc_and_calibration_draw_thousands_of_points(site: Site) -> None:
    page = site.page("engineer")
    page.goto(f"{site.base}/spc")
    page.wait_for_selector("#charts[data-points]", timeout=30000)
    points = int(page.locator("#charts").get_attribute("data-points"))
    assert points >= BULK
    # 6 offset axes, 4 cameras, the cycle time: an individuals and a moving-range chart each
    assert page.locator("#charts .uplot").count() == 22
    render_ms = float(page.locator("#charts").get_attribute("data-render-ms"))
    assert render_ms > 0  # the page measured its own drawing; its speed is not asserted
    print(f"spc: {points} points per chart, 22 charts drawn in {render_ms:.0f} ms")
    titles = page.locator("#charts h3").all_inner_texts()
    assert titles[0].startswith("Offset X (mm): individuals")
    assert page.locator("#charts p.capability").count() == 11
    assert "control limits from the first 50 points" in page.inner_text("#charts")
    site.shot(page, "spc")

    page.goto(f"{site.base}/calibration")
    page.wait_for_selector("#charts[data-points]", timeout=30000)
    titles = page.locator("#charts h3").all_inner_texts()
    assert titles == [f"Camera {c}: mean residual (px)"
                      for c in ("back_left", "back_right", "top_left", "top_right")]
    # the drift watch's report (GET /api/v1/drift), one row per camera
    page.wait_for_function("!document.querySelector('#drift').textContent.includes('loading')",
                           timeout=30000)
    assert page.locator("#drift .drift-status").inner_text().startswith("Drift watch: ")
    assert page.locator("#drift tr").count() == 1 + 4
    assert page.locator("#drift .drift-verify").inner_text() == (
        "No calibration verify recorded yet.")
    assert "station file" in page.inner_text("main")
    # the verify measures the reference part now, through the station: offered, greyed out
    # while the station is down
    verify = page.locator("button", has_text="Measure the reference part and verify")
    assert verify.count() == 1 and verify.is_disabled()
    # the hand-eye session panel says why it shows no session (the station is down)
    assert "The station is down: no session to show." in page.inner_text("#handeye")
    site.shot(page, "calibration")
    page.context.close()


def test_recipes_diff_activate_and_teach_confirmation_by_role(site: Site) -> None:
    page = site.page("operator")
    page.goto(f"{site.base}/recipes/floor_panel")
    changed = page.locator("table.diff tr.changed td:first-child").all_inner_texts()
    assert changed == ["T_rf_from_pf0.wpr", "T_rf_from_pf0.xyz"]
    assert page.locator("button", has_text="Activate").count() == 0  # operators do not
    page.goto(f"{site.base}/history/{site.ok_framed.id}")
    info, content = site.writer.store.versions.content("recipe", "floor_panel")
    recipe = recipe_from_content("floor_panel", info.version, content)
    expected = frame_offsets(np.array(site.ok_framed.record.T_rf_from_pf),
                             recipe.T_rf_from_pf0.matrix, recipe.T_pf_from_grasp.matrix,
                             recipe.robot_convention).base
    cells = page.locator("#teach-offset td").all_text_contents()
    shown = [float(c.split()[0]) for c in cells]
    assert np.allclose(shown, expected, atol=1e-3) and cells[0].endswith("mm")
    assert page.locator("#teach-open").is_disabled()  # station down
    page.context.close()

    page = site.page("engineer")
    page.goto(f"{site.base}/recipes/floor_panel")
    page.on("dialog", lambda d: d.accept())
    site.shot(page, "recipes")
    page.locator("button", has_text="Activate").click()
    page.wait_for_function("document.querySelector('tr.active td').textContent === 'v2'")
    assert [n.active_version for n in site.writer.store.versions.names("recipe")] == [2]
    page.context.close()


def test_docs_work_offline(site: Site) -> None:
    page = site.page("read")
    outside: list[str] = []

    def only_local(route: Any) -> None:
        if route.request.url.startswith(site.base):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", only_local)
    page.goto(f"{site.base}/docs")
    page.wait_for_selector(".swagger-ui .info .title", timeout=20000)
    assert "mvpose station server" in page.inner_text(".swagger-ui .info .title")
    assert page.locator(".opblock").count() > 10
    assert outside == []
    site.shot(page, "docs", full_page=False)  # Swagger UI's whole page is long and slow
    page.context.close()


@pytest.mark.timeout(300)
def test_the_trigger_form_says_the_stations_reason_and_message(
    site: Site, tmp_path: Path,
) -> None:
    """A station process behind a page of its own (simulated station 1; the site's browser):
    the form shows what the control channel answered, the reason's name and the station's
    message."""
    import stations

    from mvpose_core.station import load_station
    from server.station.client import StationClient
    from server.station.process import StationProcess

    path = stations.station_file(tmp_path, "station1", stations.relaxed_deadline)
    cfg = stations.settings_for(path, tmp_path / "var")
    station = load_station(path)
    station = station.model_copy(update={"links": {
        **station.links, "modbus": {**station.links.get("modbus", {}), "host": "127.0.0.1",
                                    "port": 0}}})
    proc = StationProcess(cfg, station, stations.runtime_options())
    proc.start()
    stopped = False
    try:
        app = create_app(cfg, StationClient(cfg.resolved_control_socket))
        with serve(app) as base:
            context = site.browser.new_context(viewport=VIEWPORT)
            try:
                page = context.new_page()
                login(page, base, stations.ENGINEER)
                msg = page.locator("section.actions .msg")
                # nothing in front of the simulated cameras yet: a refusal, in the station's words
                page.fill("#trigger-form input[name=part_id]", "VIN1")
                page.click("#trigger-form button[type=submit]")
                page.wait_for_function(
                    "() => document.querySelector('section.actions .msg').textContent !== ''")
                text = msg.inner_text()
                assert text.startswith("CAMERA_FAILED: too few marks"), text
                assert "error" in (msg.get_attribute("class") or "")
                _in_thread(lambda: proc.station.scene.set_part_pose(
                    proc.station.active.config.T_rf_from_pf0.matrix))
                page.click("#trigger-form button[type=submit]")
                page.wait_for_function(
                    "() => document.querySelector('section.actions .msg').textContent"
                    ".startsWith('OK')")
                assert "done" in (msg.get_attribute("class") or "")
                # The station goes down under an open Live page: its actions grey out, with
                # the status pushed to the page (no reload)
                actions = page.locator("section.actions button")
                assert actions.all_inner_texts() == ["Trigger now", "Arm teach"]
                assert all(not b.is_disabled() for b in actions.all())
                page.evaluate("window.__same_page = 7")
                proc.stop()
                stopped = True
                page.wait_for_function(
                    "[...document.querySelectorAll('section.actions button')].every("
                    "(b) => b.disabled)", timeout=15000)
                assert page.locator("#status .state").inner_text() == "station down"
                assert page.evaluate("window.__same_page") == 7
            finally:
                context.close()
    finally:
        if not stopped:
            proc.stop()


#: every page, and what shows it has drawn
PAGES = {"/": "#status", "/line": "#verdict", "/history": "table.history",
         "/spc": "#charts[data-points]", "/calibration": "#charts[data-points]",
         "/recipes": "table", "/recipes/floor_panel": "table.diff"}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("role", ["read", "operator", "engineer"])
def test_axe_finds_nothing_serious_on_any_page(site: Site, role: str) -> None:
    page = site.page(role)
    for path, ready in {**PAGES, f"/history/{site.framed.id}": "figure.cam img"}.items():
        page.goto(site.base + path)
        page.wait_for_selector(ready, timeout=30000)
        assert_accessible(page, f"{path} as {role}")
        assert page.locator("h1").count() == 1, path
    page.context.close()
    # and the login page, before anyone logs in
    context = site.browser.new_context(viewport=VIEWPORT)
    login_page = context.new_page()
    login_page.goto(f"{site.base}/login")
    assert_accessible(login_page, "/login")
    context.close()

