"""The SPC page (/spc) and its JSON on a seeded store: limits from the baseline, the point that
breaks rule 1, Cp/Cpk, the plant's time zone; in a real browser (one Playwright session for the
module), the charts drawn with their limits and the rule-1 point marked and listed.

The seeded series: one measured record replayed with offsets X drawn from N(0, 0.1 mm) (seed 3,
rounded to µm: a series that breaks no run rule) and one record whose X is 2.5 mm off (beyond
3σ, well inside the recipe's tolerance)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo

import numpy as np
import pytest
import stations
from asgi import running
from axe import assert_accessible
from system_packages import ensure_commands

from server.app import create_app
from server.auth import Role, create_token
from server.settings import Settings
from server.state import open_services
from server.store.schemas import Offset
from server.web.sample import SampleLine
from server.web.screenshots import VIEWPORT, launch, login, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
ZONE = "Europe/Berlin"
N = 60
OUTLIER = 45  # the index (in the window, oldest first) of the record 2.5 mm off


X = np.round(np.random.default_rng(3).normal(0, 0.1, N), 3)
X[OUTLIER] = 2.5


def _x(k: int) -> float:
    return float(X[k])


@dataclass
class Seeded:
    cfg: Settings
    ids: list[int]
    t: list[float]
    max_offset_mm: float
    token: str  # a reader's


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> Seeded:
    tmp = tmp_path_factory.mktemp("spc")

    def zone(data: dict[str, Any]) -> None:
        data["time_zone"] = ZONE

    cfg = stations.settings_for(stations.station_file(tmp, "station1", zone), tmp / "var")
    services = open_services(cfg)
    try:
        line = SampleLine(services)
        template, _ = line.record()
        assert template.offset is not None
        ids, t = [], []
        for k in range(N):
            line.trigger_id += 1
            values = list(template.offset.values)
            values[0] = _x(k)
            s = services.record_measurement(template.model_copy(update={
                "trigger_id": line.trigger_id, "part_id": f"VIN{line.trigger_id:06d}",
                "triggered_at": line.start + timedelta(seconds=line.period_s * line.trigger_id),
                "offset": Offset(convention=template.offset.convention, values=values)}))
            ids.append(s.id)
            t.append(s.record.triggered_at.timestamp())
        recipe, _ = line.recipe()
        token = create_token(services.store.tokens, "spc-read", Role.READ)[0]
        return Seeded(cfg, ids, t, recipe.tolerances.max_offset_mm, token)
    finally:
        services.close()


async def test_the_spc_json_has_limits_rules_and_capability(seeded: Seeded) -> None:
    async with running(create_app(seeded.cfg)) as (client, _):
        r = await client.post("/web/login", json={"token": seeded.token},
                              headers={"Origin": "http://station"})
        assert r.status_code == 200, r.text
        d = (await client.get("/web/spc.json", params={"limit": N, "baseline": 30})).json()
        assert d["points"] == N and d["time_zone"] == ZONE
        assert d["baseline"] == "the first 30 points of the window"
        keys = [c["key"] for c in d["charts"]]
        assert keys[:6] == [f"offset.{a}" for a in "XYZWPR"]
        assert keys[6:] == [f"rms.{c}" for c in ("back_left", "back_right", "top_left",
                                                 "top_right")] + ["cycle.total"]
        assert d["charts"][-1]["usl"] == 50.0  # the station's cycle deadline
        x = d["charts"][0]
        values = np.array([_x(k) for k in range(N)])
        base = values[:30]
        mr_bar = float(np.mean(np.abs(np.diff(base))))
        lim = x["limits"]
        assert lim["center"] == pytest.approx(base.mean(), abs=1e-6)
        assert lim["mr_center"] == pytest.approx(mr_bar, abs=1e-6)
        assert lim["ucl"] == pytest.approx(base.mean() + 3 * mr_bar / 1.128, abs=1e-6)
        assert lim["mr_ucl"] == pytest.approx(3.267 * mr_bar, abs=1e-6)
        assert lim["baseline_points"] == 30 and lim["baseline_to"] == seeded.t[29]
        assert (x["lsl"], x["usl"]) == (-seeded.max_offset_mm, seeded.max_offset_mm)
        # rule 1: exactly the seeded record
        assert [r["rule"] for r in x["rules"]] == [1]
        rule1 = x["rules"]
        assert rule1[0]["count"] == 1 and rule1[0]["western_electric"]
        assert rule1[0]["points"] == [{"id": seeded.ids[OUTLIER], "t": seeded.t[OUTLIER],
                                       "value": 2.5}]
        assert x["flagged"][OUTLIER] == 2.5 and x["values"] == pytest.approx(values.tolist())
        # Cp/Cpk over the whole window, σ within from its moving ranges
        within = float(np.mean(np.abs(np.diff(values)))) / 1.128
        overall = float(np.std(values, ddof=1))
        tol, mean = seeded.max_offset_mm, float(values.mean())
        cap = x["capability"]
        assert cap["cp"] == pytest.approx(2 * tol / (6 * within), abs=1e-3)
        assert cap["cpk"] == pytest.approx((tol - abs(mean)) / (3 * within), abs=1e-3)
        assert cap["ppk"] == pytest.approx((tol - abs(mean)) / (3 * overall), abs=1e-3)
        # Y is the same in every record: its limits collapse on it and flag nothing
        assert d["charts"][1]["limits"]["sigma_within"] == 0 and d["charts"][1]["rules"] == []
        # a camera's residual has an upper tolerance only: Cpk is its Cpu, no Cp
        rms = d["charts"][6]
        assert rms["lsl"] is None and rms["usl"] is not None and rms["capability"]["cp"] is None

        # a baseline as a time range, typed in the plant's time (CET: UTC+1 in November)
        local = [np.datetime64(int(v) + 3600, "s").astype(str) for v in seeded.t]
        d = (await client.get("/web/spc.json", params={
            "limit": N, "baseline_since": local[10], "baseline_until": local[19]})).json()
        lim = d["charts"][0]["limits"]
        assert lim["baseline_points"] == 10 and lim["baseline_from"] == seeded.t[10]
        assert lim["center"] == pytest.approx(values[10:20].mean(), abs=1e-6)

        # a baseline that ends before it starts is refused, in words
        r = await client.get("/web/spc.json", params={"baseline_since": local[19],
                                                      "baseline_until": local[10]})
        assert r.status_code == 400 and "is before baseline_since" in r.json()["detail"]
        # the old address leads to the page
        r = await client.get("/trends?limit=5", follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"] == "/spc?limit=5"


@pytest.fixture(scope="module")
def browser_site(seeded: Seeded) -> Iterator[tuple[str, Any]]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    with serve(create_app(seeded.cfg)) as base, sync_playwright() as pw:
        browser = launch(pw)
        try:
            yield base, browser
        finally:
            browser.close()


def test_the_spc_page_draws_limits_and_marks_the_rule_1_point(
    seeded: Seeded, browser_site: tuple[str, Any],
) -> None:
    base, browser = browser_site
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda err: errors.append(str(err)))
    login(page, base, seeded.token)
    page.goto(f"{base}/trends")  # the old tab's address
    assert page.url.endswith("/spc")
    page.wait_for_selector("#charts[data-points]", timeout=30000)
    assert page.locator("nav a", has_text="SPC").count() == 1
    # the default baseline (50 points) holds the outlier; the first 30 do not
    page.fill("#trend-filters input[name=baseline]", "30")
    page.click("#trend-filters button[type=submit]")
    page.wait_for_function("document.querySelector('#charts').dataset.points !== undefined && "
                           "document.querySelector('.spc-head').textContent.includes('first 30')",
                           timeout=30000)
    assert int(page.locator("#charts").get_attribute("data-points")) == N
    # 6 axes, 4 cameras and the cycle time, an individuals and a moving-range chart each
    assert page.locator("#charts section.spc").count() == 11
    assert page.locator("#charts .uplot").count() == 22
    x = page.locator("#charts section.spc[data-key='offset.X']")
    labels = x.evaluate("(b) => b.querySelector('.chart').plot.series.map((s) => s.label)")
    assert {"UCL", "centre", "LCL", "USL (tolerance)", "LSL (tolerance)",
            "run rule broken"} <= set(labels)
    marked = x.evaluate("""(b) => { const p = b.querySelector('.chart').plot;
        const k = p.series.findIndex((s) => s.label === 'run rule broken');
        return p.data[k].map((v, i) => v === null ? null : i).filter((i) => i !== null); }""")
    assert marked == [OUTLIER]
    rule = x.locator("li.rule-broken[data-rule='1']")
    assert rule.count() == 1
    text = rule.inner_text()
    assert "1 point beyond 3σ" in text and f"#{seeded.ids[OUTLIER]}" in text
    # the listed time is the plant's (Europe/Berlin, UTC+1 in November)
    local = np.datetime64(int(seeded.t[OUTLIER]) + 3600, "s").astype(str).replace("T", " ")
    assert local in text, (local, text)
    assert "Cp " in x.locator("p.capability").inner_text()
    axis = page.evaluate("document.querySelector('#charts .chart').plot.axes[0].label")
    assert axis == f"time ({ZONE})"
    # the time ticks are the plant's wall clock, on its whole minutes
    ticks = page.evaluate("""() => {
        const a = document.querySelector('#charts .chart').plot.axes[0];
        return [a._splits, a._values]; }""")
    assert len(ticks[0]) >= 2
    for t, label in zip(*ticks, strict=True):
        if label:
            assert label == datetime.fromtimestamp(t, ZoneInfo(ZONE)).strftime("%H:%M"), ticks
    assert_accessible(page, "/spc")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "spc.png"), full_page=True)
    assert not errors, errors
    context.close()
