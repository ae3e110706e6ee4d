"""Gauge studies: run one on stored measurements, list them, fetch one, download its report."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Response
from pydantic import BaseModel, ConfigDict, Field

from mvpose_core.gauge import GaugeError
from mvpose_core.station import RecipeConfig
from server.api.deps import EngineerUser, IdInt, IsoDateTime, ReadUser, ServicesDep
from server.errors import InvalidInputError, NotFoundError
from server.gauge.report import ReportHeader, to_html, to_pdf
from server.gauge.sources import Selection, StudyRequest, build_study, stored_samples
from server.gauge.study import GaugeStudy
from server.state import Services
from server.store.gauge import StoredStudy

router = APIRouter(prefix="/gauge/studies", tags=["gauge"])
StudyPath = Annotated[int, Path(ge=1, le=2**63 - 1)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class StudyCreate(BaseModel):
    """A study of stored OK measurements of one recipe, chosen by part id, time or result ids."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["type1", "type3", "linearity"]
    recipe: str | None = Field(None, max_length=64, description="default: the station's default")
    part_id: str | None = Field(None, max_length=64)
    since: IsoDateTime | None = Field(None, description="triggered at or after (with zone)")
    until: IsoDateTime | None = Field(None, description="triggered before (with zone)")
    result_ids: list[IdInt] = Field(default_factory=list, max_length=10000)
    reference: list[Finite] | None = Field(
        None, min_length=1, max_length=7,
        description="type1: the part's true offset in the recipe's convention (no Cgk without)")
    truth: dict[str, list[Finite]] = Field(
        default_factory=dict, max_length=10000,
        description="linearity: the known offset of each result id (recipe convention)")
    tolerance_mm: Finite | None = Field(None, gt=0, description="T of lengths; default 2 × "
                                        "the recipe's translation_mm")
    tolerance_deg: Finite | None = Field(None, gt=0, description="T of angles; default 2 × "
                                         "the recipe's rotation_deg")
    title: str = Field("", max_length=200)
    same_part: bool = Field(False, description="type1: the selection is one part whatever its "
                            "part ids say")


class StudyOut(BaseModel):
    """A stored study: its place in the audit chain, the verdict and its figures."""

    id: int
    seq: int
    kind: str
    recipe: str
    created_at: datetime
    created_by: str
    passed: bool
    hash: str
    prev_hash: str
    title: str
    source: dict[str, Any]
    figures: list[dict[str, Any]]
    records: list[dict[str, Any]]

    @classmethod
    def of(cls, s: StoredStudy) -> StudyOut:
        b = s.body
        return cls(id=s.id, seq=s.seq, kind=s.kind, recipe=s.recipe, created_at=s.created_at,
                   created_by=s.created_by, passed=s.passed, hash=s.hash, prev_hash=s.prev_hash,
                   title=b.get("title", ""), source=b.get("source", {}),
                   figures=b.get("figures", []), records=b.get("records", []))


class StudyListItem(BaseModel):
    id: int
    seq: int
    kind: str
    recipe: str
    created_at: datetime
    created_by: str
    passed: bool
    title: str


def recipe_of(services: Services, name: str | None) -> RecipeConfig:
    """The recipe a study holds measurements against: the station file's, else the store's
    active version."""
    if services.station is not None:
        try:
            return services.station.recipe(name)
        except KeyError as err:
            raise NotFoundError(str(err.args[0])) from None
    if name is None:
        raise InvalidInputError("recipe: name the recipe (the server has no station file)")
    _, content = services.store.versions.content("recipe", name)
    return RecipeConfig.model_validate(content)


def header(services: Services, s: StoredStudy) -> ReportHeader:
    return ReportHeader(services.station_name, s.id, s.created_at, s.created_by, s.hash)


@router.post("", response_model=StudyOut, status_code=201, summary="Run a gauge study")
def create(body: StudyCreate, user: EngineerUser, services: ServicesDep) -> StudyOut:
    """Run a study on stored measurements and seal it in the audit trail."""
    recipe = recipe_of(services, body.recipe)
    sel = Selection(part_id=body.part_id, since=body.since, until=body.until,
                    result_ids=tuple(body.result_ids))
    request = StudyRequest(kind=body.kind, reference=body.reference,
                           tolerance_mm=body.tolerance_mm, tolerance_deg=body.tolerance_deg,
                           truth=body.truth, title=body.title,
                           same_part=body.same_part)
    try:
        samples = stored_samples(services.store, recipe, sel)
        study = build_study(request, samples, recipe, sel.describe())
        content = study.to_json()
    except GaugeError as err:
        raise InvalidInputError(str(err)) from None
    return StudyOut.of(services.store.gauge.add(content, user.name))


@router.get("", response_model=list[StudyListItem], summary="List gauge studies")
def list_studies(_: ReadUser, services: ServicesDep) -> list[StudyListItem]:
    """The newest 100 studies first."""
    return [StudyListItem(id=s.id, seq=s.seq, kind=s.kind, recipe=s.recipe,
                          created_at=s.created_at, created_by=s.created_by, passed=s.passed,
                          title=s.body.get("title", ""))
            for s in services.store.gauge.newest()]


@router.get("/{study_id}", response_model=StudyOut, summary="One gauge study")
def get_study(study_id: StudyPath, _: ReadUser, services: ServicesDep) -> StudyOut:
    """A study with its figures and the records it used (result id and hash)."""
    return StudyOut.of(services.store.gauge.get(study_id))


@router.get("/{study_id}/report.html", response_class=Response, summary="Report (HTML)",
            responses={200: {"content": {"text/html": {}}}})
def report_html(study_id: StudyPath, _: ReadUser, services: ServicesDep) -> Response:
    """The study's report as one self-contained HTML page, plots included."""
    s = services.store.gauge.get(study_id)
    text = to_html(GaugeStudy.from_json(s.body), header(services, s))
    return Response(text, media_type="text/html; charset=utf-8")


@router.get("/{study_id}/report.pdf", response_class=Response, summary="Report (PDF)",
            responses={200: {"content": {"application/pdf": {}}}})
def report_pdf(study_id: StudyPath, _: ReadUser, services: ServicesDep) -> Response:
    """The study's report as a PDF: header, verdict, figures and sign-off, then the plots."""
    s = services.store.gauge.get(study_id)
    pdf = to_pdf(GaugeStudy.from_json(s.body), header(services, s))
    return Response(pdf, media_type="application/pdf", headers={
        "Content-Disposition": f'attachment; filename="gauge-study-{s.id}.pdf"'})
