"""Operator page: Gauge studies (docs/gauge.md): the stored studies, and one with its plots."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, Request
from fastapi.responses import HTMLResponse

from server.auth import Principal
from server.errors import NotFoundError
from server.gauge.report import STYLE, TITLES, ReportHeader, fragment
from server.gauge.study import GaugeStudy
from server.store.gauge import StoredStudy
from server.web import html, i18n
from server.web.context import in_thread, page_user
from server.web.i18n import N_, _
from server.web.pages import Html, to_login

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
StudyPath = Annotated[int, Path(ge=1, le=2**63 - 1)]
API = "/api/v1/gauge/studies"


@router.get("/gauge")
async def gauge_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    services = request.state.services
    studies: list[StoredStudy] = await in_thread(services.store.gauge.newest)
    rows = "".join(
        f"<tr><td><a href='/gauge/{s.id}'>{s.id}</a></td><td>{html.when(s.created_at)}</td>"
        f"<td>{html.esc(TITLES.get(s.kind, s.kind))}</td><td>{html.esc(s.recipe)}</td>"
        f"<td>{html.esc(s.body.get('title', ''))}</td><td>{html.esc(s.created_by)}</td>"
        f"<td class='{'pass' if s.passed else 'fail'}'>"
        + html.esc(_('passed') if s.passed else _('FAILED')) + f"</td>"
        f"<td><a href='{API}/{s.id}/report.pdf'>PDF</a></td></tr>" for s in studies)
    e = html.esc
    heads = "".join("<th>" + e(_(h)) + "</th>" for h in (
        N_("study"), N_("created"), N_("kind"), N_("recipe"), N_("title"), N_("by"),
        N_("verdict")))
    table = (f"<table class='gauge'><tr>{heads}<th><span class='visually-hidden'>"
             + e(_('report')) + f"</span></th></tr>{rows}</table>" if studies else
             "<p class='muted'>" + e(_('No gauge study stored yet.')) + "</p>")
    intro = e(_("Type-1 (Cg, Cgk ≥ 1.33), type-3 (%GRR, ndc) and linearity studies of this "
                "station, each sealed in the audit trail. Run one with {cli} or {api} "
                "(engineer); docs/gauge.md.")).format(cli="<code>mvpose gauge</code>",
                                                      api=f"<code>POST {API}</code>")
    body = (f"<style>{STYLE}</style><section class='panel'><h2>" + e(_('Gauge studies')) + f"</h2>"
            f"<p>{intro}</p>{table}</section>")
    return html_response(_("Gauge studies"), user, body)


@router.get("/gauge/{study_id}")
async def study_page(request: Request, study_id: StudyPath) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    services = request.state.services
    try:
        s: StoredStudy = await in_thread(services.store.gauge.get, study_id)
    except NotFoundError as err:
        body = f"<section class='panel'><p>{html.esc(err)}</p></section>"
        return html_response(_("Gauge study"), user, body, status=404)
    header = ReportHeader(services.station_name, s.id, s.created_at, s.created_by, s.hash)
    inner = await in_thread(fragment, GaugeStudy.from_json(s.body), header)
    body = (f"<style>{STYLE}</style><section class='panel'><h2>{html.esc(TITLES[s.kind])}</h2>"
            f"<p><a href='/gauge'>" + html.esc(_('all studies')) + "</a> · "
            + html.esc(_('report:')) + f" <a href='{API}/{s.id}/report.html'>"
            f"HTML</a> · <a href='{API}/{s.id}/report.pdf'>PDF</a></p>{inner}</section>")
    return html_response(_("Gauge study {id}").format(id=s.id), user, body)


def html_response(title: str, user: Principal, body: str, status: int = 200) -> Html:
    return HTMLResponse(html.layout(title, user, body, "/gauge"), status_code=status)
