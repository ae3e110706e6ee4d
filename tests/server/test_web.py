"""The operator page through the real app (ASGI): session login, CSRF, roles, overlays, data.

The browser-driven tests are in test_web_browser.py; these check what the server answers.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import anyio.to_thread
import cv2
import numpy as np
import pytest
from apps import ENGINEER, settings
from asgi import running

from mvpose_core.scene import project_recipe_marks, view_cameras
from server.app import create_app
from server.auth import Role, create_token
from server.state import Services
from server.store.schemas import StoredMeasurement
from server.web.reader import Reader
from server.web.sample import SampleLine
from server.web.session import COOKIE

ORIGIN = {"Origin": "http://station"}


async def _login(client: object, token: str) -> None:
    r = await client.post("/web/login", json={"token": token}, headers=ORIGIN)  # type: ignore[attr-defined]
    assert r.status_code == 200, r.text


async def _tokens(services: Services) -> dict[str, str]:
    out = {}
    for role in (Role.READ, Role.OPERATOR):
        secret, _ = await anyio.to_thread.run_sync(create_token, services.store.tokens,
                                                   f"web-{role.value}", role)
        out[role.value] = secret
    return out | {"engineer": ENGINEER}


async def _sample(services: Services, frames: bool = False) -> list[StoredMeasurement]:
    line = SampleLine(services)

    def run() -> list[StoredMeasurement]:
        out = line.run(6, missing_every=3)
        if frames:
            out.append(line.store(*line.record(missing="B2", frames=True)))
        return out

    return await anyio.to_thread.run_sync(run)


async def test_login_sets_a_strict_http_only_session_that_the_rest_api_accepts(
    tmp_path: Path,
) -> None:
    async with running(create_app(settings(tmp_path, sqlite_synchronous="NORMAL"))) as (
        client, state):
        assert (await client.get("/")).headers["location"] == "/login?next=/"
        r = await client.post("/web/login", json={"token": "mvp_wrong-token-0123456789"},
                              headers=ORIGIN)
        assert r.status_code == 401 and COOKIE not in r.headers.get("set-cookie", "")
        r = await client.post("/web/login", json={"token": ENGINEER},
                              headers={"Origin": "http://evil.example"})
        assert r.status_code == 403, "a login form on another site must not log in here"
        r = await client.post("/web/login", json={"token": ENGINEER}, headers=ORIGIN)
        cookie = r.headers["set-cookie"]
        assert r.json() == {"name": "bootstrap", "role": "engineer", "idle_logout_s": 900.0}
        assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie
        assert ENGINEER not in cookie, "the cookie holds a session id, never the token"
        assert (await client.get("/")).status_code == 200
        # the page's own reads of the REST API go with the cookie
        assert (await client.get("/api/v1/measurements")).status_code == 200
        # a state-changing request with the cookie must come from this page
        body = {"name": "t", "role": "read"}
        r = await client.post("/api/v1/tokens", json=body)
        assert r.status_code == 403 and "Origin" in r.json()["detail"]
        r = await client.post("/api/v1/tokens", json=body, headers={"Origin": "http://evil.x"})
        assert r.status_code == 403
        r = await client.post("/api/v1/tokens", json=body, headers=ORIGIN)
        assert r.status_code == 201, r.text
        # logging out ends the session server-side: the old cookie is worthless
        sid = client.cookies[COOKIE]
        assert (await client.post("/web/logout", headers=ORIGIN)).status_code == 200
        client.cookies.set(COOKIE, sid)
        assert (await client.get("/")).status_code == 303
        assert (await client.get("/api/v1/measurements")).status_code == 401
        client.cookies.clear()
        # a revoked token ends its sessions at once
        services: Services = state["services"]
        tokens = await _tokens(services)
        await _login(client, tokens["read"])
        assert (await client.get("/history")).status_code == 200
        await anyio.to_thread.run_sync(services.store.tokens.revoke, "web-read")
        assert (await client.get("/history")).status_code == 303


@pytest.mark.parametrize(("role", "shown", "hidden"), [
    ("read", [], ["Trigger now", "Arm teach", "Teach this", "Activate"]),
    ("operator", ["Trigger now", "Arm teach", "Teach this"], ["Activate"]),
    ("engineer", ["Trigger now", "Arm teach", "Teach this", "Activate"], []),
])
async def test_the_page_shows_only_the_actions_the_role_may_do(
    tmp_path: Path, role: str, shown: list[str], hidden: list[str],
) -> None:
    async with running(create_app(settings(tmp_path, sqlite_synchronous="NORMAL"))) as (
        client, state):
        services: Services = state["services"]
        stored = await _sample(services)
        ok = next(s for s in stored if s.record.result == "OK")
        line = SampleLine(services)
        await anyio.to_thread.run_sync(line.taught_version, ok)
        await _login(client, (await _tokens(services))[role])
        pages = ""
        for path in ("/", f"/history/{ok.id}", "/recipes/floor_panel"):
            r = await client.get(path)
            assert r.status_code == 200, path
            pages += r.text
        for words in shown:
            assert words in pages, f"{role} should see {words!r}"
        for words in hidden:
            assert words not in pages, f"{role} must not see {words!r}"
        # and the server refuses what the page does not show
        r = await client.post("/web/actions/activate", json={"name": "floor_panel", "version": 2},
                              headers=ORIGIN)
        assert r.status_code == (200 if role == "engineer" else 403), r.text
        if role == "engineer":  # station down: recorded in the store for its next start
            assert "station down" in r.json()["message"]
            names = await anyio.to_thread.run_sync(services.store.versions.names, "recipe")
            assert names[0].active_version == 2
        # the station's actions answer 503 with the station down, whatever the role allows
        r = await client.post("/web/actions/trigger", json={}, headers=ORIGIN)
        assert r.status_code == (403 if role == "read" else 503), r.text


async def test_overlays_are_the_records_detections_windows_and_residuals(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path, sqlite_synchronous="NORMAL"))) as (
        client, state):
        services: Services = state["services"]
        stored = await _sample(services, frames=True)
        nok = stored[-1]
        reader = Reader(services)
        view = await anyio.to_thread.run_sync(reader.get, nok.id)
        assert view.has_frames and len(view.overlays) == 4
        recipe = view.recipe
        assert recipe is not None and services.station is not None
        cams = {(c.view, c.camera_id): c for c in view_cameras(services.station)}
        T = np.array(nok.record.T_rf_from_pf)
        all_res = []
        for ov in view.overlays:
            reproj = {pm.mark_id: pm.uv for pm in
                      project_recipe_marks(cams[(ov.view, ov.camera_id)], recipe, T)}
            for m in ov.marks:
                assert m.window is not None and m.predicted is not None
                u0, v0, u1, v1 = m.window
                assert u0 <= m.predicted[0] <= u1 and v0 <= m.predicted[1] <= v1
                if m.found:
                    assert m.uv is not None and m.residual is not None
                    assert u0 <= m.uv[0] <= u1 and v0 <= m.uv[1] <= v1
                    assert np.allclose(m.residual, np.subtract(m.uv, reproj[m.mark_id]))
                    all_res.append(m.residual)
                else:
                    assert m.mark_id == "B2" and m.reason
        # the residuals drawn are the pose engine's own: same RMS as the record's
        rms = math.sqrt(np.mean(np.sum(np.square(all_res), axis=1)))
        assert nok.record.residuals is not None
        assert rms == pytest.approx(nok.record.residuals.rms_px, rel=1e-6)

        await _login(client, ENGINEER)
        page = (await client.get(f"/history/{nok.id}")).text
        circles = re.findall(r'class="found" data-mark="(\w+)" data-u="([\d.]+)" '
                             r'data-v="([\d.]+)"', page)
        found = {(d.mark_id): d.uv for cd in nok.record.detections for d in cd.detections
                 if d.found}
        assert len(circles) == len(found) == 7
        for mark, u, v in circles:
            assert math.hypot(float(u) - found[mark][0], float(v) - found[mark][1]) < 1e-3
        assert page.count('class="missing" data-mark="B2"') == 1
        assert page.count('class="window"') == 8
        # frames: downscaled JPEG of the archived PNG
        r = await client.get(f"/web/frames/{nok.id}/1/top_left", params={"w": 512})
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape == (512, 512)
        r = await client.get(f"/web/frames/{stored[0].id}/1/top_left")
        assert r.status_code == 404 and "no archived frame" in r.json()["detail"]


async def test_history_pages_like_the_rest_api_and_trends_have_every_column(
    tmp_path: Path,
) -> None:
    async with running(create_app(settings(tmp_path, sqlite_synchronous="NORMAL"))) as (
        client, state):
        services: Services = state["services"]
        stored = await _sample(services)
        await _login(client, ENGINEER)
        ids: list[int] = []
        url: str | None = "/history?limit=4&result=OK"
        while url:
            text = (await client.get(url)).text
            ids += [int(x) for x in re.findall(r'<tr class="ok" data-id="(\d+)"', text)]
            nxt = re.search(r'class="more" href="([^"]+)"', text)
            url = nxt.group(1).replace("&amp;", "&") if nxt else None
        rest = (await client.get("/api/v1/measurements", params={"result": "OK"})).json()
        assert ids == [i["id"] for i in rest["items"]] == [
            s.id for s in reversed(stored) if s.record.result == "OK"]
        assert 'href="/api/v1/measurements/export?format=csv&amp;result=OK"' in text
        d = (await client.get("/web/trends.json", params={"limit": 5})).json()
        cols, tol = d["columns"], d["tolerances"]
        assert cols["id"] == [s.id for s in stored[-5:]]
        assert cols["cameras"] == ["back_left", "back_right", "top_left", "top_right"]
        for key in ("t", "sigma_mm", "sigma_deg", "rms_px", "total_ms", "result", "reason"):
            assert len(cols[key]) == 5, key
        assert len(cols["offset"]) == 6 and all(len(c) == 5 for c in cols["camera_rms"].values())
        assert tol["labels"] == ["X", "Y", "Z", "W", "P", "R"] and tol["deadline_ms"] == 50.0
        nok = [k for k, r in enumerate(cols["result"]) if r == "NOK"]
        assert nok and all(cols["offset"][0][k] is None for k in nok)


async def test_docs_and_page_assets_are_served_by_the_app(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        docs = (await client.get("/docs")).text
        urls = re.findall(r'(?:src|href|url)\s*[=:]\s*["\']([^"\']+)', docs)
        assert urls and all(u.startswith("/") for u in urls), urls
        for u in urls:
            assert (await client.get(u)).status_code == 200, u
        assert (await client.get("/redoc")).status_code == 404  # no CDN-only page left
        login = (await client.get("/login")).text
        for asset in re.findall(r'(?:src|href)="(/static/[^"]+)"', login):
            r = await client.get(asset)
            assert r.status_code == 200 and len(r.content) > 1000, asset
        r = await client.get("/static/vendor/jquery.js")
        assert r.status_code == 404 and "is not one of" in r.json()["detail"]
        # an open redirect after login is refused
        r = await client.get("/login", params={"next": "//evil.example/x"})
        assert 'data-next="/"' in r.text


def test_status_panel_reads_the_station_status() -> None:
    from server.web.html import status_panel

    status = {"station": "station1", "state": "READY", "deadline_ms": 50.0,
              "recipe": {"name": "floor_panel", "version": 3, "number": 1, "sha256": "ab" * 32},
              "calibration": {"id": "cal-7", "sha256": "cd" * 32}, "teach_armed": True,
              "cameras": {"top_left": "up (0 reconnects)", "top_right": "down: timeout"},
              "links": {"modbus": {"running": True, "state": "READY", "plc_online": False,
                                   "server_heartbeat": 12}},
              "counts": {"triggers": 5, "ok": 4, "nok": 1}}
    shift = "early 06:00–14:00 UTC: OK 40 · NOK 2"
    panel = status_panel(status, None, "station file", shift)
    for words in ("READY", "modbus: READY · PLC offline", "floor_panel v3", "cal-7 (cdcdcdcdcdcd)",
                  "top_right: down: timeout", shift, "teach armed"):
        assert words in panel, words
    # the counts are the store's (the shift's), not the station process's memory
    assert "triggers 5" not in panel
    assert "12" not in panel.replace("cdcdcdcdcdcd", "")  # the heartbeat is not shown
    down = status_panel(None, "the station process is not running", "station file", shift)
    assert "station down" in down and "not running" in down and shift in down


async def test_a_station_that_does_not_answer_is_shown_down(tmp_path: Path) -> None:
    from server.station.client import StationClient

    station = StationClient(tmp_path / "no-station.sock", timeout_s=0.5)
    async with running(create_app(settings(tmp_path), station)) as (client, _):
        await _login(client, ENGINEER)
        page = (await client.get("/")).text
        assert "station down" in page and "the station process is not running" in page
        # the engineer's actions stay on the page, disabled while the station is down
        assert re.search(r"<button type=\"submit\" data-needs-station disabled[^>]*>\s*"
                         r"Trigger now", page)
        r = await client.post("/web/actions/trigger", json={"part_id": "VIN1"}, headers=ORIGIN)
        assert r.status_code == 503 and "not running" in r.json()["detail"]


@pytest.mark.timeout(300)
async def test_the_trigger_message_names_the_stations_reason_and_message(tmp_path: Path) -> None:
    import stations

    from server.loopback import move_part, running_server
    from server.station.client import StationClient

    path = stations.station_file(tmp_path, "station1", stations.relaxed_deadline)
    st_settings = stations.settings_for(path, tmp_path / "var")
    async with running_server(st_settings, stations.runtime_options(), http_port=None) as srv:
        rt = srv.runtime
        app = create_app(st_settings, StationClient(st_settings.resolved_control_socket))
        async with running(app) as (client, _):
            await _login(client, stations.ENGINEER)
            # no part in front of the simulated cameras yet: a refusal, with the station's words
            r = await client.post("/web/actions/trigger", json={"part_id": "VIN1"},
                                  headers=ORIGIN)
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["reason"] == "CAMERA_FAILED" and body["result_code"] != 0
            assert body["message"].startswith("CAMERA_FAILED: too few marks"), body
            assert "nothing to see" in body["message"]
            await move_part(rt, None, rt.active.config.T_rf_from_pf0.matrix)  # type: ignore[arg-type]
            r = await client.post("/web/actions/trigger", json={"part_id": "VIN2"},
                                  headers=ORIGIN)
            body = r.json()
            assert body["reason"] == "OK" and body["result_code"] == 0, body
            assert body["message"] == "OK", body  # the gate's "OK" is not said twice
            assert body["measurement_id"] is not None
