"""Users on the operator page in a real browser (Debian's Chromium through Playwright): login by
PIN, a wrong PIN, the lockout, the idle logout, a disabled user's open page, and the kiosk.

Three apps on real sockets share one SQLite store with no station process: the station file's
defaults, a short idle logout (``page: {idle_logout_s: 5}``), and a kiosk (``page: {kiosk:
true}``). Screenshots go to var/screenshots/.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import stations
from apps import settings
from axe import assert_accessible
from system_packages import ensure_commands
from waiting import until_sync

from server.app import create_app
from server.auth import Role
from server.state import Services, open_services
from server.users import FREE_TRIES, SecretKind, add_user
from server.web.html import TABS
from server.web.screenshots import VIEWPORT, launch, login_user, serve

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "var" / "screenshots"
IDLE_S = 5  # the short idle logout of the idle app; long enough for a page to load in


@dataclass
class Users:
    base: str
    idle: str  # the same store, page.idle_logout_s = IDLE_S
    kiosk: str  # the same store, page.kiosk = true
    browser: Any
    services: Services

    def page(self) -> Any:
        page = self.browser.new_context(viewport=VIEWPORT).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.errors = errors
        return page

    def add(self, name: str, role: Role, pin: str) -> None:
        _in_thread(lambda: add_user(self.services.store.users, name, role, SecretKind.PIN, pin,
                                    "test"))


def _in_thread(fn: Any) -> Any:
    """A store call off the test's thread (Playwright's sync API runs a loop in this one)."""
    out: list[Any] = []
    t = threading.Thread(target=lambda: out.append(fn()))
    t.start()
    t.join(60)
    return out[0]


def _page(**page: Any) -> Any:
    return lambda data: data.update(page=page)


@pytest.fixture(scope="module")
def users(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Users]:
    ensure_commands({"chromium": "chromium"})
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("users")
    files = {}
    for name, edit in (("plain", _page()), ("idle", _page(idle_logout_s=IDLE_S)),
                       ("kiosk", _page(kiosk=True))):
        (tmp / name).mkdir()
        files[name] = stations.station_file(tmp / name, "station1", edit)
    cfg = settings(tmp, station=files["plain"])
    services = open_services(cfg)
    try:
        with serve(create_app(cfg)) as base, \
                serve(create_app(cfg.model_copy(update={"station": files["idle"]}))) as idle, \
                serve(create_app(cfg.model_copy(update={"station": files["kiosk"]}))) as kiosk, \
                sync_playwright() as pw:
            browser = launch(pw)
            try:
                yield Users(base, idle, kiosk, browser, services)
            finally:
                browser.close()
    finally:
        services.close()


def _shot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"))
    print(f"screenshot: {SHOTS / name}.png")
    assert not page.errors, page.errors


def _try(page: Any, base: str, user: str, pin: str) -> str:
    """Submit the login form; the message it shows (waited for)."""
    if not page.url.startswith(f"{base}/login"):
        page.goto(f"{base}/login")
    page.fill("input[name=user]", user)
    page.fill("input[name=secret]", pin)
    msg = page.locator("#login-form + .msg")
    page.evaluate("document.querySelector('#login-form + .msg').textContent = ''")
    page.click("#login-form button[type=submit]")
    page.wait_for_function("document.querySelector('#login-form + .msg').textContent !== ''")
    return str(msg.text_content())


def test_a_user_logs_in_with_a_pin(users: Users) -> None:
    users.add("anna", Role.OPERATOR, "4711")
    page = users.page()
    page.goto(f"{users.base}/line")
    assert page.url == f"{users.base}/login?next=/line"
    assert "logs out after 15 min without a click" in page.locator("main").inner_text()
    assert page.locator("input[name=secret]").get_attribute("type") == "password"
    assert not page.locator("input[name=token]").is_visible(), "the token login is folded"
    assert_accessible(page, "/login")
    _shot(page, "users-login")
    page.fill("input[name=user]", "anna")
    page.fill("input[name=secret]", "4711")
    page.click("#login-form button[type=submit]")
    page.wait_for_url(f"{users.base}/line")
    assert page.locator("header .who").inner_text().startswith("anna")
    assert page.locator("header .who b").get_attribute("data-role") == "operator"
    page.click("#logout")
    page.wait_for_url(f"{users.base}/login")
    assert page.request.get(f"{users.base}/web/session").status == 401
    assert not page.errors, page.errors
    page.context.close()


def test_a_wrong_pin_is_refused_with_a_message(users: Users) -> None:
    users.add("ben", Role.OPERATOR, "1234")
    page = users.page()
    said = _try(page, users.base, "ben", "4321")
    assert said == "unknown user or wrong PIN or password"
    assert page.url.startswith(f"{users.base}/login")
    assert page.locator("#login-form + .msg").get_attribute("role") == "alert"
    assert_accessible(page, "/login, wrong PIN")
    _shot(page, "users-wrong-pin")
    assert page.request.get(f"{users.base}/web/session").status == 401
    page.context.close()


def test_repeated_wrong_pins_lock_the_user_out(users: Users) -> None:
    users.add("carl", Role.OPERATOR, "2468")
    page = users.page()
    said = [_try(page, users.base, "carl", f"000{i}") for i in range(FREE_TRIES)]
    assert said[-1] == f"wrong PIN, {FREE_TRIES} in a row for 'carl': try again in 30 s"
    # now even the right PIN waits: it is not checked at all
    said = _try(page, users.base, "carl", "2468")
    assert "'carl': try again in" in said
    assert page.url.startswith(f"{users.base}/login")
    _shot(page, "users-lockout")
    events = _in_thread(lambda: users.services.store.users.events("carl"))
    assert [e.event for e in events][:2] == ["login_refused", "login_failed"]
    page.context.close()


def test_an_idle_page_logs_out_and_an_active_one_does_not(users: Users) -> None:
    users.add("dora", Role.OPERATOR, "1357")
    idle, active = users.page(), users.page()
    for page in (idle, active):
        login_user(page, users.idle, "dora", "1357")
        page.wait_for_function(f"document.body.dataset.idleLogoutS === '{IDLE_S}'")
    # The Live page's events and the status keep arriving on both; only the active one is used.
    pressed = [0]

    def idle_one_left() -> bool:
        active.keyboard.press("Shift")
        active.mouse.wheel(0, 10)
        pressed[0] += 1
        return idle.url.startswith(f"{users.idle}/login")

    until_sync(idle_one_left, "the idle page goes to the login", timeout_s=IDLE_S + 30,
               every_s=0.2)
    assert idle.url == f"{users.idle}/login?next=%2F&idle=1"
    assert idle.locator("#idle-note").is_visible()
    _shot(idle, "users-idle-logout")
    assert pressed[0] > 1
    assert active.url == f"{users.idle}/", "the page in use stays logged in"
    assert active.request.get(f"{users.idle}/web/session").status == 200
    assert idle.request.get(f"{users.idle}/web/session").status == 401
    assert not active.errors, active.errors
    idle.context.close()
    active.context.close()


def test_a_role_change_and_a_disable_reach_the_users_open_page(users: Users) -> None:
    users.add("emil", Role.OPERATOR, "9753")
    page = users.page()
    login_user(page, users.base, "emil", "9753")
    assert page.locator("#trigger-form").count() == 1  # an operator's action
    _in_thread(lambda: users.services.store.users.set_role("emil", "read", "test"))
    page.wait_for_selector("header .who b[data-role=read]", timeout=20000)
    assert page.locator("#trigger-form").count() == 0, "a read user is offered no action"
    assert page.url == f"{users.base}/"
    _in_thread(lambda: users.services.store.users.disable("emil", "test"))
    page.wait_for_url(f"{users.base}/login?next=%2F", timeout=20000)
    said = _try(page, users.base, "emil", "9753")
    assert said == "user 'emil' is disabled; an engineer enables it again"
    page.context.close()


def test_the_kiosk_shows_the_line_view_read_only_and_every_other_page_needs_a_login(
        users: Users) -> None:
    page = users.page()
    page.goto(f"{users.kiosk}/line")
    assert page.url == f"{users.kiosk}/line"
    page.wait_for_selector("#line-view")
    assert page.locator("button, input, select, textarea, form").count() == 0, \
        "no control on the kiosk"
    assert page.locator("header nav a").count() == 0
    assert page.locator("script[src='/static/session.js']").count() == 0
    assert_accessible(page, "/line, kiosk")
    _shot(page, "users-kiosk")
    for href, _ in TABS:
        if href == "/line":
            continue
        page.goto(f"{users.kiosk}{href}")
        assert page.url.startswith(f"{users.kiosk}/login"), href
    for url in ("/api/v1/measurements", "/web/session", "/api/v1/users"):
        assert page.request.get(f"{users.kiosk}{url}").status == 401, url
    refused = page.request.post(f"{users.kiosk}/web/actions/trigger",
                                headers={"Origin": users.kiosk}, data={})
    assert refused.status == 401
    # the same line view elsewhere (no kiosk setting) needs a login
    page.goto(f"{users.base}/line")
    assert page.url.startswith(f"{users.base}/login")
    page.context.close()
