"""The operator page's languages: gettext catalogues through Babel, the request's language, and
numbers, dates and times in its locale and the plant's time zone.

English is the source; server/web/locale/<code>/LC_MESSAGES/messages.po holds each other
language's catalogue, compiled to messages.mo by the install (``make venv``, the Dockerfile:
``pybabel compile -d server/web/locale``). A request's language is the user's choice on the page
(cookie :data:`COOKIE`), else the station file's ``page.language``, else the browser's
``Accept-Language``, else English. Page functions call :func:`_` and the formatters here; the
request's language is set once per request (:func:`page_language`, a router dependency) or
around a rendering (:func:`use`). The core's English reason texts are mapped to messages here
(:func:`reason_words`, :func:`check_words`), never translated in mvpose_core.
"""

from __future__ import annotations

import gettext
import logging
import math
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from datetime import datetime
from functools import cache
from pathlib import Path
from zoneinfo import ZoneInfo

from babel import Locale
from babel.dates import format_date, format_skeleton
from babel.numbers import format_decimal
from babel.support import Translations
from fastapi import Request

from mvpose_core.reasons import CHECKS, DESCRIPTIONS, Reason
from mvpose_core.shifts import time_zone
from mvpose_core.station import PAGE_LANGUAGES

log = logging.getLogger(__name__)

#: each language's name in itself (the page's selector)
LANGUAGES = {"en": "English", "de": "Deutsch", "zh_Hans": "简体中文", "es": "Español"}
SOURCE = "en"
#: the user's choice, set by the page's selector (app.js); a year
COOKIE = "mvpose_lang"
LOCALE_DIR = Path(__file__).resolve().parent / "locale"
DOMAIN = "messages"
assert tuple(LANGUAGES) == PAGE_LANGUAGES, "the station file's languages are the page's"


def N_(message: str) -> str:  # noqa: N802 (gettext's name for "mark for extraction")
    """Mark ``message`` for the catalogue without translating it here."""
    return message


@dataclass(frozen=True)
class Lang:
    """One request's language: its locale, its catalogue and the plant's time zone."""

    code: str
    locale: Locale
    translations: gettext.NullTranslations
    zone_name: str
    zone: ZoneInfo

    @property
    def html_lang(self) -> str:
        """The BCP 47 tag for ``<html lang>``: ``zh-Hans``, ``de``."""
        return self.code.replace("_", "-")


def catalogue_path(code: str, suffix: str = "mo") -> Path:
    return LOCALE_DIR / code / "LC_MESSAGES" / f"{DOMAIN}.{suffix}"


@cache
def translations(code: str) -> gettext.NullTranslations:
    """The compiled catalogue of ``code`` (English: none). A checkout whose install has not
    compiled the catalogues yet reads the .po (and says so in the log)."""
    if code == SOURCE:
        return gettext.NullTranslations()
    mo = catalogue_path(code)
    po = catalogue_path(code, "po")
    if mo.exists() and mo.stat().st_mtime >= po.stat().st_mtime:
        with mo.open("rb") as f:
            return Translations(f, domain=DOMAIN)
    import io

    from babel.messages.mofile import write_mo
    from babel.messages.pofile import read_po

    log.warning("operator page: %s is missing or older than its .po; run `pybabel compile -d "
                "%s` (make venv does)", mo, LOCALE_DIR)
    with po.open("rb") as f:
        cat = read_po(f, locale=code)
    buf = io.BytesIO()
    write_mo(buf, cat)
    buf.seek(0)
    return Translations(buf, domain=DOMAIN)


@cache
def lang(code: str, zone_name: str = "UTC") -> Lang:
    if code not in LANGUAGES:
        raise ValueError(f"language {code!r} is not one of the page's: {', '.join(LANGUAGES)}")
    return Lang(code, Locale.parse(code), translations(code), zone_name, time_zone(zone_name))


_current: ContextVar[Lang | None] = ContextVar("mvpose_page_lang", default=None)


def current() -> Lang:
    found = _current.get()
    return found if found is not None else lang(SOURCE)


@contextmanager
def use(code: str, zone_name: str = "UTC") -> Iterator[Lang]:
    """Render in ``code`` with times in ``zone_name`` (a thread of its own, a live feed)."""
    token = _current.set(lang(code, zone_name))
    try:
        yield current()
    finally:
        _current.reset(token)


# ---------------------------------------------------------------------------- which language
def _accepted(header: str) -> list[str]:
    """``de-DE,de;q=0.9,en;q=0.8`` → ``["de-DE", "de", "en"]``, by quality."""
    ranked = []
    for n, part in enumerate(header.split(",")[:32]):
        tag, _sep, params = part.strip().partition(";")
        q = 1.0
        for p in params.split(";"):
            k, _sep, v = p.strip().partition("=")
            if k == "q":
                try:
                    q = float(v)
                except ValueError:
                    q = 0.0
        if tag and q > 0:
            ranked.append((-q, n, tag.strip()))
    return [tag for _q, _n, tag in sorted(ranked)]


def from_tag(tag: str) -> str | None:
    """The page's language for a BCP 47 tag: ``de-AT`` → de, ``zh-CN`` / ``zh-Hans`` → zh_Hans
    (``zh-TW`` / ``zh-Hant``, Traditional Chinese, → None)."""
    parts = tag.replace("_", "-").lower().split("-")
    if parts[0] == "zh":
        rest = parts[1:]
        if "hant" in rest or any(r in ("tw", "hk", "mo") for r in rest):
            return None
        return "zh_Hans"
    return parts[0] if parts[0] in LANGUAGES else None


def choose(cookie: str | None, plant: str | None, accept_language: str | None) -> str:
    """The user's choice, else the plant's default, else the browser's, else English."""
    if cookie in LANGUAGES:
        return str(cookie)
    if plant in LANGUAGES:
        return str(plant)
    for tag in _accepted(accept_language or ""):
        code = from_tag(tag)
        if code is not None:
            return code
    return SOURCE


def request_lang(request: Request) -> Lang:
    station = request.state.services.station
    plant = station.page.language if station is not None else None
    zone = station.time_zone if station is not None else "UTC"
    code = choose(request.cookies.get(COOKIE), plant, request.headers.get("accept-language"))
    return lang(code, zone)


async def page_language(request: Request) -> None:
    """Router dependency: the page functions of this request speak its language. (An async
    dependency runs in the endpoint's own task, so the setting reaches the endpoint and the
    worker threads it starts.)"""
    _current.set(request_lang(request))


# ---------------------------------------------------------------------------- messages
def _(message: str) -> str:
    return current().translations.gettext(message)


def ngettext(singular: str, plural: str, n: int) -> str:
    return current().translations.ngettext(singular, plural, n)


def reason_words(code: int) -> str:
    """mvpose_core.reasons.describe in the page's language."""
    try:
        return _(DESCRIPTIONS[Reason(code)])
    except (ValueError, KeyError):
        return _("unknown result code {code}").format(code=code)


def check_words(code: int) -> str:
    """mvpose_core.reasons.what_to_check in the page's language."""
    try:
        return _(CHECKS[Reason(code)])
    except (ValueError, KeyError):
        return _("the record's message and the log")


# The core's English texts (mvpose_core/reasons.py), marked here for the catalogue: the
# extractor reads only literals, so each is listed once. tests/server/test_i18n.py checks that
# this list is the core's tables.
CORE_TEXTS = (
    N_("measured within every tolerance"),
    N_("marks the recipe needs were not found"),
    N_("the pose estimate did not converge"),
    N_("the marks do not fit the part model (RMS residual too high)"),
    N_("one mark does not fit the part model (largest residual too high)"),
    N_("the rotation is too uncertain for the grasp"),
    N_("the position is too uncertain for the grasp"),
    N_("the part is shifted further than the recipe allows"),
    N_("the part is turned further than the recipe allows"),
    N_("the measurement input was invalid"),
    N_("too few marks were seen to fix the pose"),
    N_("the marks seen do not fix the pose"),
    N_("a mark lies behind a camera at the estimated pose"),
    N_("a camera gave no image"),
    N_("an image was refused (wrong size or format)"),
    N_("the result was not ready within the cycle deadline"),
    N_("the selected recipe does not exist on this station"),
    N_("the view index is not one of the recipe's views"),
    N_("software fault (see the log)"),
    N_("the result could not be stored"),
    N_("no answer within the link's deadline"),
    N_("the station failed to answer (see the log)"),
    N_("the station's answer could not be encoded for the link"),
    N_("refused: the station is busy"),
    N_("unknown command"),
    N_("command argument out of range"),
    N_("nothing: the offset was sent"),
    N_("dirt on a mark, the lighting, the part off its place"),
    N_("a mark mix-up or a bad calibration"),
    N_("a false mark, a moved camera, a stale calibration"),
    N_("marks seen too close together; the recipe's tolerance"),
    N_("the part's place on the fixture (max_offset_mm)"),
    N_("the part's place on the fixture (max_offset_deg)"),
    N_("the recipe and the station file (the record's message says what)"),
    N_("dirt, the lighting, a camera's view blocked"),
    N_("the recipe's marks and sightings (too few in one line)"),
    N_("a mark mix-up or a camera's pose in the calibration"),
    N_("the camera's cable, power and status on the Live page"),
    N_("the camera's image size and pixel format against the station file"),
    N_("the cycle time chart on SPC; a slow camera or a busy machine"),
    N_("the recipe number the PLC sends"),
    N_("the view index the PLC sends"),
    N_("the log: it has the traceback; call the engineer"),
    N_("the disk (full?) and the database"),
    N_("a stuck camera or detector: the camera's status, the log"),
    N_("the log: the station failed to answer"),
    N_("the log: the answer did not fit the link's format"),
    N_("the PLC's handshake: a trigger sent while one was running"),
    N_("the command code the PLC sends"),
    N_("the command argument the PLC sends"),
)


# ---------------------------------------------------------------------------- formats
def num(x: float | None, digits: int = 3) -> str:
    """``x`` with ``digits`` decimals in the locale (``1,250`` in German), no grouping."""
    if x is None or not math.isfinite(x):
        return "—"
    pattern = "0." + "0" * digits if digits > 0 else "0"
    return str(format_decimal(round(x, digits) + 0.0, format=pattern, locale=current().locale))


def pct(x: float | None, digits: int = 1) -> str:
    """``95.3 %`` / ``95,3 %``: a percentage already times 100."""
    return "—" if x is None else f"{num(x, digits)} %"


def when(t: datetime | None) -> str:
    """A moment in the plant's time, the locale's date and 24-hour time, and the zone's
    abbreviation: ``Nov 2, 2026, 07:00:00 CET`` / ``02.11.2026, 07:00:00 MEZ``."""
    if t is None:
        return "—"
    cur = current()
    local = t.astimezone(cur.zone)
    loc = cur.locale
    both = str(loc.datetime_formats["medium"]).replace("{0}", "\0").replace("{1}", "\1")
    stamp = both.replace("\1", format_date(local, "medium", locale=loc)).replace(
        "\0", format_skeleton("Hms", local, locale=loc))
    return f"{stamp} {local.tzname() or cur.zone_name}"


def clock(t: datetime) -> str:
    """``07:00``: the wall-clock time in the plant."""
    return t.astimezone(current().zone).strftime("%H:%M")
