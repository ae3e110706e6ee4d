"""Operator page: Gauge studies (docs/gauge.md): the stored studies, and one with its plots."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import HTMLResponse

from server.auth import Principal
from server.errors import NotFoundError
from server.gauge.report import STYLE, TITLES, ReportHeader, fragment
from server.gauge.study import GaugeStudy
from server.store.gauge import StoredStudy
from server.web import html
from server.web.context import in_thread, page_user
from server.web.pages import Html, to_login

router = APIRouter(include_in_schema=False)
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
        f"<td class='{'pass' if s.passed else 'fail'}'>{'passed' if s.passed else 'FAILED'}</td>"
        f"<td><a href='{API}/{s.id}/report.pdf'>PDF</a></td></tr>" for s in studies)
    table = ("<table class='gauge'><tr><th>study</th><th>created</th><th>kind</th>"
             f"<th>recipe</th><th>title</th><th>by</th><th>verdict</th><th></th></tr>{rows}"
             "</table>" if studies else
             "<p class='muted'>No gauge study stored yet.</p>")
    body = (f"<style>{STYLE}</style><section class='panel'><h2>Gauge studies</h2>"
            "<p>Type-1 (Cg, Cgk ≥ 1.33), type-3 (%GRR, ndc) and linearity studies of this "
            "station, each sealed in the audit trail. Run one with <code>mvpose gauge</code> or "
            f"<code>POST {API}</code> (engineer); docs/gauge.md.</p>{table}</section>")
    return html_response("Gauge studies", user, body)


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
        return html_response("Gauge study", user, body, status=404)
    header = ReportHeader(services.station_name, s.id, s.created_at, s.created_by, s.hash)
    inner = await in_thread(fragment, GaugeStudy.from_json(s.body), header)
    body = (f"<style>{STYLE}</style><section class='panel'><h2>{html.esc(TITLES[s.kind])}</h2>"
            f"<p><a href='/gauge'>all studies</a> · report: <a href='{API}/{s.id}/report.html'>"
            f"HTML</a> · <a href='{API}/{s.id}/report.pdf'>PDF</a></p>{inner}</section>")
    return html_response(f"Gauge study {s.id}", user, body)


def html_response(title: str, user: Principal, body: str, status: int = 200) -> Html:
    return HTMLResponse(html.layout(title, user, body, "/gauge"), status_code=status)
