"""Users of the operator page through the real app (ASGI) and the CLI: PIN and password
logins, hashing, the lockout, audit, the admin endpoints, and sessions that follow a user's
changes (disable, reset, role) and end after idle time."""

from __future__ import annotations

import os
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio.to_thread
import pytest
import sqlalchemy as sa
import stations
from apps import ENGINEER, settings
from asgi import running

from server.app import create_app
from server.store import open_store
from server.users import FIRST_WAIT_S, FREE_TRIES, LOCK_AFTER, login, verify_secret
from server.web.session import COOKIE, Sessions, Who

ROOT = Path(__file__).resolve().parents[2]
ORIGIN = {"Origin": "http://station"}
ADMIN = {"Authorization": f"Bearer {ENGINEER}"}


async def _add(client: Any, name: str, role: str, secret: str, kind: str = "pin") -> Any:
    return await client.post("/api/v1/users", headers=ADMIN,
                             json={"name": name, "role": role, "kind": kind, "secret": secret})


async def _login(client: Any, user: str, secret: str) -> Any:
    return await client.post("/web/login", json={"user": user, "secret": secret},
                             headers=ORIGIN)


def _page_config(**page: Any) -> Any:
    def edit(data: dict[str, Any]) -> None:
        data["page"] = page
    return edit


async def test_an_engineer_adds_users_whose_secrets_are_stored_as_salted_scrypt(
        tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, state):
        r = await _add(client, "anna", "operator", "4711")
        assert r.status_code == 201, r.text
        assert r.json()["role"] == "operator" and r.json()["secret_kind"] == "pin"
        assert (await _add(client, "ben", "operator", "4711")).status_code == 201
        assert (await _add(client, "eva", "engineer", "correct horse battery",
                           "password")).status_code == 201
        # the secret's rules, named; never the value
        bad = await _add(client, "carl", "operator", "47a")
        assert bad.status_code == 422 and "a PIN has 4 to 8 digits" in bad.json()["detail"]
        assert "47a" not in bad.text
        short = await _add(client, "carl", "engineer", "short", "password")
        assert short.status_code == 422 and "10 to 200 characters" in short.json()["detail"]
        assert (await _add(client, "carl", "engineer", "1234", "token")).status_code == 422
        assert (await _add(client, "anna", "read", "1234")).status_code == 409
        # engineers only
        r = await client.post("/api/v1/tokens", headers=ADMIN,
                              json={"name": "op", "role": "operator"})
        op = {"Authorization": f"Bearer {r.json()['token']}"}
        assert (await client.get("/api/v1/users", headers=op)).status_code == 403
        listed = await client.get("/api/v1/users", headers=ADMIN)
        assert [u["name"] for u in listed.json()] == ["anna", "ben", "eva"]
        assert "secret_hash" not in listed.json()[0]

        engine = state["services"].store.engine
        with engine.connect() as conn:
            rows = dict(conn.execute(sa.text("SELECT name, secret_hash FROM users")).all())
        assert rows["anna"].startswith("scrypt$16384$8$1$")
        assert rows["anna"] != rows["ben"], "the same PIN, each with its own salt"
        assert "4711" not in rows["anna"]
        assert verify_secret("4711", rows["anna"]) and not verify_secret("4712", rows["anna"])
        with engine.connect() as conn:
            events = conn.execute(sa.text("SELECT user_name, event, actor FROM user_events "
                                          "ORDER BY id")).all()
        assert [tuple(e) for e in events] == [("anna", "created", "bootstrap"),
                                              ("ben", "created", "bootstrap"),
                                              ("eva", "created", "bootstrap")]
        with pytest.raises(sa.exc.DatabaseError, match="append-only"), engine.begin() as conn:
            conn.execute(sa.text("DELETE FROM user_events"))


async def test_a_user_logs_in_with_a_pin_and_the_page_knows_the_users_name(
        tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        await _add(client, "anna", "operator", "4711")
        wrong = await _login(client, "anna", "4712")
        assert wrong.status_code == 401
        unknown = await _login(client, "nobody", "4711")
        assert unknown.status_code == 401
        assert wrong.json()["detail"] == unknown.json()["detail"], \
            "a wrong PIN and an unknown user read the same"
        assert COOKIE not in wrong.headers.get("set-cookie", "")
        r = await _login(client, "anna", "4711")
        assert r.status_code == 200, r.text
        assert r.json()["name"] == "anna" and r.json()["role"] == "operator"
        assert "4711" not in r.headers["set-cookie"]
        me = (await client.get("/web/session")).json()
        assert me["name"] == "anna" and me["role"] == "operator"
        assert me["idle_logout_s"] == 900.0
        # the REST API takes the user's session as the page's reads do
        assert (await client.get("/api/v1/measurements")).status_code == 200
        page = await client.get("/")
        assert page.status_code == 200 and "anna" in page.text
        assert "/static/session.js" in page.text
        # the audit trail, for an engineer
        trail = await client.get("/api/v1/user-events", params={"user": "anna"},
                                 headers=ADMIN)
        assert [e["event"] for e in trail.json()] == ["login", "login_failed", "created"]
        assert trail.json()[1]["detail"].startswith("wrong secret 1 in a row from page ")


async def test_wrong_pins_make_the_user_wait_and_then_lock_it_until_a_reset(
        tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, state):
        await _add(client, "anna", "operator", "4711")
        codes = [(await _login(client, "anna", f"000{i}")).status_code
                 for i in range(FREE_TRIES)]
        assert codes == [401] * (FREE_TRIES - 1) + [429]
        # waiting: even the right PIN is not checked now
        r = await _login(client, "anna", "4711")
        assert r.status_code == 429 and "try again in" in r.json()["detail"]

        # on, past each wait (the policy's clock is a parameter)
        repo = state["services"].store.users
        now, wait = datetime.now(UTC), FIRST_WAIT_S
        for _ in range(FREE_TRIES, LOCK_AFTER):
            now += timedelta(seconds=wait + 1)
            with pytest.raises(Exception) as err:
                await anyio.to_thread.run_sync(login, repo, "anna", "0000", "test", now)
            wait *= 2
        assert "is now locked after 10 wrong PINs" in str(err.value)
        far = now + timedelta(days=1)
        with pytest.raises(Exception, match="is locked"):
            await anyio.to_thread.run_sync(login, repo, "anna", "4711", "test", far)
        assert (await _login(client, "anna", "4711")).status_code == 403
        info = (await client.get("/api/v1/users/anna", headers=ADMIN)).json()
        assert info["locked_at"] is not None and info["failed_count"] == LOCK_AFTER

        r = await client.post("/api/v1/users/anna/reset", headers=ADMIN,
                              json={"kind": "pin", "secret": "271828"})
        assert r.status_code == 200 and r.json()["locked_at"] is None
        assert (await _login(client, "anna", "271828")).status_code == 200
        events = [e["event"] for e in (await client.get(
            "/api/v1/user-events", params={"user": "anna", "limit": 50},
            headers=ADMIN)).json()]
        assert events.count("login_failed") == LOCK_AFTER
        assert events.count("locked") == 1 and "login_refused" in events
        assert events[:2] == ["login", "reset"]


async def test_disabling_a_user_ends_its_sessions_at_once(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        await _add(client, "anna", "operator", "4711")
        assert (await _login(client, "anna", "4711")).status_code == 200
        assert (await client.get("/web/session")).status_code == 200
        r = await client.patch("/api/v1/users/anna", headers=ADMIN, json={"disabled": True})
        assert r.status_code == 200 and r.json()["disabled_at"] is not None
        assert (await client.get("/web/session")).status_code == 401
        assert (await client.get("/")).headers["location"] == "/login?next=/"
        assert (await client.get("/api/v1/measurements")).status_code == 401
        refused = await _login(client, "anna", "4711")
        assert refused.status_code == 403 and "disabled" in refused.json()["detail"]
        # enabled again, the old session stays over: a new login is needed
        await client.patch("/api/v1/users/anna", headers=ADMIN, json={"disabled": False})
        assert (await client.get("/web/session")).status_code == 401
        assert (await _login(client, "anna", "4711")).status_code == 200


async def test_a_reset_ends_the_users_sessions(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        await _add(client, "anna", "operator", "4711")
        await _login(client, "anna", "4711")
        await client.post("/api/v1/users/anna/reset", headers=ADMIN,
                          json={"kind": "pin", "secret": "1234"})
        assert (await client.get("/web/session")).status_code == 401
        assert (await _login(client, "anna", "4711")).status_code == 401
        assert (await _login(client, "anna", "1234")).status_code == 200


async def test_a_role_change_applies_to_open_sessions(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        await _add(client, "anna", "operator", "4711")
        await _login(client, "anna", "4711")
        # an operator may arm teach: without a station process it is 503, not 403
        assert (await client.post("/web/actions/arm-teach", headers=ORIGIN)).status_code == 503
        assert (await client.post("/web/actions/activate", headers=ORIGIN, json={
            "name": "floor_panel", "version": 1})).status_code == 403
        r = await client.patch("/api/v1/users/anna", headers=ADMIN, json={"role": "read"})
        assert r.json()["role"] == "read"
        denied = await client.post("/web/actions/arm-teach", headers=ORIGIN)
        assert denied.status_code == 403 and "'read'" in denied.json()["detail"]
        assert (await client.get("/web/session")).json()["role"] == "read"
        await client.patch("/api/v1/users/anna", headers=ADMIN, json={"role": "engineer"})
        assert (await client.post("/web/actions/activate", headers=ORIGIN, json={
            "name": "floor_panel", "version": 1})).status_code == 200
        events = [e["event"] for e in (await client.get(
            "/api/v1/user-events", params={"user": "anna"}, headers=ADMIN)).json()]
        assert events[:2] == ["role", "role"]


async def test_the_login_takes_a_user_or_a_token_never_both(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        for body in ({}, {"user": "anna"}, {"secret": "4711"},
                     {"user": "anna", "secret": "4711", "token": ENGINEER},
                     {"user": "a b", "secret": "4711"}):
            r = await client.post("/web/login", json=body, headers=ORIGIN)
            assert r.status_code == 422, body
        assert (await client.post("/web/login", json={"token": ENGINEER},
                                  headers=ORIGIN)).status_code == 200


def test_a_session_ends_after_idle_time_counted_from_user_actions() -> None:
    now = [1000.0]
    sessions = Sessions(clock=lambda: now[0])
    sid = sessions.open(Who(user="anna"))
    now[0] += 250
    assert sessions.get(sid, 300) == Who(user="anna")  # a look is not an action
    assert sessions.idle_left_s(sid, 300) == 50
    now[0] += 60
    assert sessions.get(sid, 300) is None, "idle for 310 s of 300"
    assert sessions.get(sid, 3600) is None, "an ended session stays ended"
    sid = sessions.open(Who(user="anna"))
    for _ in range(5):
        now[0] += 250
        sessions.touch(sid)
        assert sessions.get(sid, 300) is not None


async def test_only_user_actions_restart_the_idle_time(tmp_path: Path) -> None:
    path = stations.station_file(tmp_path, "station1", _page_config(idle_logout_s=300))
    app = create_app(settings(tmp_path, station=path))
    now = [1000.0]
    app.state.web_sessions.clock = lambda: now[0]  # the sessions' clock is a parameter
    clicked = {"Sec-Fetch-Mode": "navigate", "Sec-Fetch-User": "?1"}
    async with running(app) as (client, _):
        await _add(client, "anna", "operator", "4711")
        await _login(client, "anna", "4711")

        async def left() -> float:
            r = await client.get("/web/session")
            return float(r.json()["idle_left_s"]) if r.status_code == 200 else -1.0

        now[0] += 200
        assert await left() == 100
        # background reads and a page the browser loaded by itself are not actions
        for url in ("/", "/line", "/web/line/fragment", "/api/v1/measurements"):
            assert (await client.get(url)).status_code == 200, url
        assert await left() == 100
        assert (await client.get("/", headers=clicked)).status_code == 200
        assert await left() == 300, "a page opened by a click is an action"
        now[0] += 200
        r = await client.post("/web/session/activity", headers=ORIGIN)
        assert r.json()["idle_left_s"] == 300, "the page reports a click or a key"
        now[0] += 301
        assert (await client.get("/web/session")).status_code == 401
        assert (await client.get("/", headers=clicked)).headers["location"] == "/login?next=/"


def test_the_cli_adds_lists_disables_and_resets_users(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MVPOSE_")}
    data = ["--data-dir", str(tmp_path / "var")]

    def mvpose(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "server.cli", "user", *args, *data],
                              input=stdin, capture_output=True, text=True, env=env, cwd=ROOT,
                              timeout=120)

    r = mvpose("add", "anna", "--role", "operator", "--pin", stdin="4711\n")
    assert r.returncode == 0, r.stderr
    assert "user 'anna' (operator, PIN) added" in r.stderr and "4711" not in r.stderr + r.stdout
    bad = mvpose("add", "ben", "--role", "operator", "--pin", stdin="12\n")
    assert bad.returncode == 1 and "4 to 8 digits" in bad.stderr
    empty = mvpose("add", "ben", "--role", "operator", "--pin")
    assert empty.returncode == 2 and "no PIN on standard input" in empty.stderr
    assert mvpose("disable", "anna").returncode == 0
    listed = mvpose("list")
    line = next(x for x in listed.stdout.splitlines() if x.startswith("anna"))
    assert "operator" in line and "pin" in line and line.count("T") >= 2  # created, disabled
    r = mvpose("reset", "anna", "--password", stdin="a long password\n")
    assert r.returncode == 0, r.stderr
    assert mvpose("enable", "anna").returncode == 0
    missing = mvpose("disable", "nobody")
    assert missing.returncode == 1 and "user 'nobody' does not exist" in missing.stderr
    trail = mvpose("events", "anna").stdout
    assert [x.split()[2] for x in trail.splitlines()[1:]] == [
        "enabled", "reset", "disabled", "created"]

    store = open_store(f"sqlite:///{tmp_path / 'var' / 'mvpose.db'}", "station1")
    try:
        assert login(store.users, "anna", "a long password", "test").principal.name == "anna"
    finally:
        store.close()


def test_the_kiosk_is_a_station_file_setting_and_the_old_variable_stops_the_start(
        tmp_path: Path) -> None:
    from mvpose_core.station import load_station

    path = stations.station_file(tmp_path, "station1", _page_config(kiosk=True))
    assert load_station(path).page.kiosk is True
    assert load_station(stations.station_file(tmp_path, "station1")).page.kiosk is False
    typo = stations.station_file(tmp_path, "station1", _page_config(kisok=True))
    with pytest.raises(Exception, match="kisok"):
        load_station(typo)
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MVPOSE_")},
           "MVPOSE_LINE_VIEW_PUBLIC": "true"}
    r = subprocess.run([sys.executable, "-m", "server.cli", "api", "--port", "0"], env=env,
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "page: {kiosk: true}" in r.stderr
