"""The Prometheus scrape endpoint (the metrics themselves live in server/metrics.py).

The station process's counters and histograms come over its control channel at each scrape; a
station that does not answer leaves them out (``mvpose_station_up 0``), never the scrape.
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from server.api.deps import ServicesDep, station_of
from server.errors import NotReadyError
from server.metrics import scrape

log = logging.getLogger(__name__)

router = APIRouter(tags=["metrics"])


@router.get(
    "/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}}
)
def metrics(request: Request, services: ServicesDep) -> Response:
    """Prometheus text exposition (no token needed: no part data in it)."""
    station = station_of(request.app)
    text: str | None = None
    if station is not None:
        try:
            text = station.metrics_text()
        except NotReadyError:
            pass  # the station is down: its metrics are missing, mvpose_station_up says so
        except Exception as err:  # noqa: BLE001 - the scrape goes on with the API's own metrics
            log.warning("the station's metrics could not be read: %s", err)
    try:
        body = scrape(services.metrics.registry, text, station is not None)
    except ValueError as err:
        log.warning("the station's metrics are not Prometheus text: %s", err)
        body = scrape(services.metrics.registry, None, station is not None)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
