"""The operator page's languages: the catalogues are complete and compile, the code's messages
are the catalogues', the request's language is chosen as documented, and numbers and times are
the locale's. The pages in a real browser, per language, are in test_web_i18n_browser.py."""

from __future__ import annotations

import io
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import stations
from asgi import running
from babel.messages.extract import extract_from_dir
from babel.messages.mofile import read_mo, write_mo
from babel.messages.pofile import read_po
from babel.support import Translations
from pydantic import ValidationError

from mvpose_core.calibration.codes import HandEyeCode
from mvpose_core.reasons import CHECKS, DESCRIPTIONS
from mvpose_core.spc import RULES
from mvpose_core.station import PAGE_LANGUAGES, load_station
from server.app import create_app
from server.station import alarms as alarm_watch
from server.store.alarms import Alarm
from server.web import alarms as web_alarms
from server.web import handeye, i18n, jstext, spc

ROOT = Path(__file__).resolve().parents[2]
LOCALES = ROOT / "server" / "web" / "locale"
TRANSLATED = [c for c in i18n.LANGUAGES if c != i18n.SOURCE]
ORIGIN = {"Origin": "http://station"}
PLACEHOLDER = re.compile(r"\{\w*\}")


def _catalogue(code: str) -> Any:
    with (LOCALES / code / "LC_MESSAGES" / "messages.po").open("rb") as f:
        return read_po(f, locale=code)


def _code_messages() -> set[Any]:
    """What the extractor finds in server/web now (babel.cfg's method and keywords)."""
    found = extract_from_dir(str(ROOT / "server" / "web"), [("**.py", "python")],
                             keywords={"_": None, "ngettext": (1, 2), "N_": None})
    return {msg for _file, _line, msg, _comments, _context in found}


def test_the_template_holds_every_message_of_the_code() -> None:
    """`make messages` was run after the last change of the page's English texts."""
    with (LOCALES / "messages.pot").open("rb") as f:
        template = {m.id for m in read_po(f) if m.id}
    code = _code_messages()
    assert code - template == set(), "messages missing from messages.pot: run `make messages`"
    assert template - code == set(), "messages.pot holds messages the code no longer has"


@pytest.mark.parametrize("code", TRANSLATED)
def test_each_catalogue_translates_every_message_and_compiles(code: str) -> None:
    cat = _catalogue(code)
    assert str(cat.locale) == code
    ids = {m.id for m in cat if m.id}
    assert ids == _code_messages(), f"{code}: catalogue and code differ: run `make messages`"
    for m in cat:
        if not m.id:
            continue
        assert "fuzzy" not in m.flags, f"{code}: {m.id!r} is fuzzy (unreviewed)"
        singular = m.id[0] if isinstance(m.id, tuple) else m.id
        plural = m.id[1] if isinstance(m.id, tuple) else m.id
        strings = m.string if isinstance(m.string, tuple) else (m.string,)
        assert len(strings) == (cat.num_plurals if isinstance(m.id, tuple) else 1), m.id
        for s in strings:
            assert s.strip(), f"{code}: {m.id!r} has no translation"
            # every {name} the page fills in is kept, and no other
            want = sorted(set(PLACEHOLDER.findall(singular)) | set(PLACEHOLDER.findall(plural)))
            assert sorted(set(PLACEHOLDER.findall(s))) == want, (code, m.id, s)
    assert not list(cat.check()), f"{code}: {list(cat.check())}"
    buf = io.BytesIO()
    write_mo(buf, cat)
    buf.seek(0)
    assert len(read_mo(buf)) == len(cat)
    buf.seek(0)
    translations = Translations(buf)
    assert translations.gettext("History") == cat["History"].string != "History"


def test_the_industrial_words_for_ok_and_nok() -> None:
    words = {c: (_catalogue(c)["OK"].string, _catalogue(c)["NOK"].string) for c in TRANSLATED}
    assert words == {"de": ("i.O.", "n.i.O."), "zh_Hans": ("合格", "不合格"),
                     "es": ("OK", "NOK")}


def test_the_core_texts_and_the_scripts_messages_are_listed_for_the_catalogue() -> None:
    # the reason texts and hints of mvpose_core.reasons, mapped to messages on the page side
    assert set(i18n.CORE_TEXTS) == set(DESCRIPTIONS.values()) | set(CHECKS.values())
    assert set(spc.RULE_NAMES) == {r.name for r in RULES.values()}
    # app.js translates through t("...") with the messages the page hands it
    script = (ROOT / "server" / "web" / "static" / "app.js").read_text()
    used = set(re.findall(r'\bt\("((?:[^"\\]|\\.)*)"', script))
    used |= {m for m in re.findall(r'"([^"]+)"', script) if m in jstext.MESSAGES}
    joined = set(re.findall(r'\bt\("((?:[^"\\]|\\.)*)" \+\s*"((?:[^"\\]|\\.)*)"', script))
    used = {u for u in used if not any(u == a for a, _ in joined)} | {a + b for a, b in joined}
    assert used - set(jstext.MESSAGES) == set(), "app.js shows messages jstext.py lacks"
    with i18n.use("de"):
        block = jstext.catalogue()
    assert block["lang"] == "de" and block["messages"]["loading…"] == "wird geladen…"


def test_reason_words_and_hints_in_each_language() -> None:
    assert i18n.reason_words(1) == "marks the recipe needs were not found"
    with i18n.use("de"):
        assert i18n.reason_words(1) == "vom Rezept benötigte Marken wurden nicht gefunden"
        assert i18n.check_words(1).startswith("Schmutz auf einer Marke")
        assert i18n.reason_words(4242) == "unbekannter Ergebniscode 4242"
    with i18n.use("zh_Hans"):
        assert i18n.reason_words(0) == "测量结果在所有公差内"


@pytest.mark.parametrize(("cookie", "plant", "accept", "want"), [
    (None, None, None, "en"),
    (None, None, "de-DE,de;q=0.9,en;q=0.8", "de"),
    (None, None, "fr-FR, es;q=0.5, de;q=0.4", "es"),
    (None, None, "zh-CN,zh;q=0.9", "zh_Hans"),
    (None, None, "zh-Hans-SG", "zh_Hans"),
    (None, None, "zh-TW, en;q=0.1", "en"),  # Traditional Chinese is not Simplified
    (None, None, "de;q=0, es", "es"),
    (None, None, "fr", "en"),
    (None, "de", "es", "de"),  # the plant's default before the browser's
    ("zh_Hans", "de", "es", "zh_Hans"),  # the user's choice before both
    ("klingon", "es", "de", "es"),  # a cookie naming no language of the page counts for nothing
])
def test_the_language_is_the_users_then_the_plants_then_the_browsers(
        cookie: str | None, plant: str | None, accept: str | None, want: str) -> None:
    assert i18n.choose(cookie, plant, accept) == want


def test_numbers_dates_and_times_in_the_locale_and_the_plants_zone() -> None:
    t = datetime(2026, 11, 2, 6, 0, 5, tzinfo=UTC)
    got = {}
    for code in i18n.LANGUAGES:
        with i18n.use(code, "Europe/Berlin"):
            got[code] = (i18n.num(-1.25, 3), i18n.pct(95.25), i18n.when(t), i18n.clock(t))
    assert got["en"] == ("-1.250", "95.2 %", "Nov 2, 2026, 07:00:05 CET", "07:00")
    assert got["de"] == ("-1,250", "95,2 %", "02.11.2026, 07:00:05 CET", "07:00")
    assert got["es"][:2] == ("-1,250", "95,2 %") and "2 nov 2026" in got["es"][2]
    assert got["zh_Hans"][0] == "-1.250" and got["zh_Hans"][2].startswith("2026年11月2日")
    with i18n.use("de"):
        assert i18n.num(None) == "—" and i18n.num(float("nan")) == "—"
        assert i18n.num(-0.0001, 2) == "0,00"  # never "-0,00"


def test_the_station_file_names_the_plants_language(tmp_path: Path) -> None:
    assert tuple(i18n.LANGUAGES) == PAGE_LANGUAGES

    def german(data: dict[str, Any]) -> None:
        data["page"] = {"language": "de"}

    assert load_station(stations.station_file(tmp_path, "station1", german)).page.language == "de"

    def typo(data: dict[str, Any]) -> None:
        data["page"] = {"language": "german"}

    with pytest.raises((ValidationError, ValueError)) as err:
        load_station(stations.station_file(tmp_path, "station1", typo))
    assert "page.language" in str(err.value) or "language" in str(err.value)


async def test_the_pages_speak_the_requests_language(tmp_path: Path) -> None:
    def plant(data: dict[str, Any]) -> None:
        data["page"] = {"language": "es"}
        data["time_zone"] = "Europe/Berlin"

    cfg = stations.settings_for(stations.station_file(tmp_path, "station1", plant),
                                tmp_path / "var")
    async with running(create_app(cfg)) as (client, _state):
        login = await client.get("/login")
        assert '<html lang="es">' in login.text and "Iniciar sesión" in login.text
        # the JSON block app.js reads: the language, the plant's zone, the script's messages
        assert '"lang":"es","zone":"Europe/Berlin"' in login.text
        r = await client.post("/web/login", json={"token": stations.ENGINEER}, headers=ORIGIN)
        assert r.status_code == 200
        page = (await client.get("/history")).text
        assert '<html lang="es">' in page and "Historial" in page and "Exportar" in page
        # the user's choice (the selector's cookie) before the plant's default
        client.cookies.set(i18n.COOKIE, "zh_Hans")
        page = (await client.get("/history", headers={"Accept-Language": "de"})).text
        assert '<html lang="zh-Hans">' in page and "历史" in page
        assert '<option value="zh_Hans" lang="zh-Hans" selected>简体中文</option>' in page
        # a refused filter says what is wrong in the page's language
        r = await client.get("/history", params={"since": "gestern", "fragment": "1"})
        assert r.status_code == 400 and "不是 ISO 8601 时间" in r.text
        client.cookies.set(i18n.COOKIE, "de")
        line = (await client.get("/line")).text
        assert '<html lang="de">' in line and "Diese Schicht" in line and "Ausbeute" in line
        spc_json = (await client.get("/web/spc.json", params={"limit": 5})).json()
        assert spc_json["baseline"] == "die ersten 50 Punkte des Fensters"
        assert spc_json["charts"][-1]["title"] == "Zykluszeit (ms)"


async def test_a_kiosk_speaks_the_plants_language_and_offers_no_choice(tmp_path: Path) -> None:
    def plant(data: dict[str, Any]) -> None:
        data["page"] = {"language": "de", "kiosk": True}

    cfg = stations.settings_for(stations.station_file(tmp_path, "station1", plant),
                                tmp_path / "var")
    async with running(create_app(cfg)) as (client, _state):
        line = await client.get("/line", headers={"Accept-Language": "es"})
        assert line.status_code == 200
        assert '<html lang="de">' in line.text and "Diese Schicht" in line.text
        assert 'id="lang-select"' not in line.text  # read-only: no control at all
        # the login page offers the choice before anyone is logged in
        assert 'id="lang-select"' in (await client.get("/login")).text


def _alarm(code: str, text: str, args: dict[str, Any]) -> Alarm:
    return Alarm(id=1, station="station1", source="test", code=code, priority="high", text=text,
                 text_key=f"alarm.{code}", text_args=args, raised_at=datetime.now(UTC),
                 cleared_at=None, acked_at=None, acked_by=None)


def test_every_alarm_code_has_a_message_and_is_said_from_its_arguments() -> None:
    # the watch's codes and the supervisor's STATION_DOWN; NOK_STREAK is a plural of its own
    assert set(alarm_watch.CODES) | {"STATION_DOWN"} == set(web_alarms.TEXTS) | {"NOK_STREAK"}
    with i18n.use("de"):
        down = _alarm("CAMERA_DOWN", "camera left1 is down: timeout",
                      {"camera": "left1", "reason": "timeout"})
        assert web_alarms.words(down) == "Kamera left1 ist ausgefallen: timeout"
        streak = _alarm("NOK_STREAK", "3 NOK results in a row (recipe door)",
                        {"count": 3, "recipe": "door"})
        assert web_alarms.words(streak) == "3 n.i.O.-Ergebnisse in Folge (Rezept door)"
        age = _alarm("CALIBRATION_AGE", "…", {"version": 4, "age_days": 31.5,
                                              "limit_days": 30, "created": "2026-10-27"})
        assert web_alarms.words(age) == ("die Kalibrierung (Version 4) ist 31,5 Tage alt; die "
                                         "Grenze ist 30 Tage")
        assert web_alarms.count_words(1, 2) == "1 aktiver Alarm (2 nicht quittiert)"
        # an alarm without the arguments its message names, or of a code the page does not
        # know, shows the English text it was stored with
        assert web_alarms.words(_alarm("LINK_DOWN", "link x is down", {})) == "link x is down"
        assert web_alarms.words(_alarm("NEW_CODE", "something new", {"a": 1})) == "something new"


def test_hand_eye_codes_are_named_in_the_language() -> None:
    assert set(handeye.CODE_WORDS) == set(HandEyeCode)
    with i18n.use("de"):
        assert handeye.code_words(int(HandEyeCode.BOARD_NOT_FOUND)) == (
            "Kalibrierplatte nicht gefunden")
        assert handeye.code_words(999) == "999"
