"""The live camera view (/cameras): each camera's newest frame with its focus and light figures,
for setting focus and light by hand.

It needs the operator role: an open view makes the station grab frames (its cameras expose
between triggers), an action on the station like "Trigger now", which a read-only screen must
not cause. The page holds one EventSource on :func:`events`; one :class:`CameraFeed` per
process asks the station (control channel ``camera_view``) for the newest frame set while at
least one browser listens, and only then: the last one to leave stops it, and the station grabs
nothing more (it grabs on request only, at most once per its period, and only between
triggers; server/station/camera_view.py). Each new set goes to every listener as one ``frames``
event (JSON: the JPEGs as data URLs and the figures).
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import anyio.to_thread
from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, StreamingResponse

from server.auth import Role
from server.web import html, i18n
from server.web.context import need, page_user, runtime_of
from server.web.fanout import Fanout, sse
from server.web.i18n import N_, _
from server.web.pages import Html, to_login

if TYPE_CHECKING:  # server.app imports this package
    from server.app import StationHandle
    from server.station.messages import CameraViewAnswer

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
#: the frames' width in the page, px (the station downscales to it)
WIDTH = 640
#: how long the feed waits before asking a station that did not answer again
DOWN_RETRY_S = 2.0


@dataclass
class CameraFeed:
    """Fan-out of the station's newest frame set to every open camera view of this process."""

    app: Any
    fan: Fanout = field(default_factory=lambda: Fanout("web-camera-feed"))
    last: str = ""  # the newest "frames" (or "down") event, for a browser that joins
    # requests sent to the station so far, and those it has answered (or that failed): the tests
    # count them. An ask the feed drops when it stops before its worker thread sent it is
    # neither; one already sent is answered after the feed stopped.
    asks: int = 0
    answered: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def listeners(self) -> int:
        return self.fan.listeners

    @property
    def running(self) -> bool:
        return self.fan.running

    def stream(self) -> AsyncIterator[str]:
        """Every event for one camera view: the newest frame set first, then each new one."""
        return self.fan.stream(self._watch, lambda: [self.last] if self.last else [])

    def _publish(self, message: str) -> None:
        self.last = message
        self.fan.publish(message)

    async def _watch(self) -> None:
        seq: int | None = None
        while True:
            station = runtime_of(self.app)
            if station is None:
                self._publish(sse("down", "this server has no station process"))
                return
            try:
                answer = await self._ask(station)
            except Exception as err:  # noqa: BLE001 - a station that cannot answer is down
                seq = None
                self._publish(sse("down", f"the station does not answer: {err}"))
                await asyncio.sleep(DOWN_RETRY_S)
                continue
            if answer.seq != seq or not self.last.startswith("event: frames"):
                seq = answer.seq
                self._publish(sse("frames", json.dumps(_payload(answer.model_dump(mode="json")),
                                                       separators=(",", ":"))))
            await asyncio.sleep(answer.period_s)

    async def _ask(self, station: StationHandle) -> CameraViewAnswer:
        """The station's answer to one ``camera_view`` request, sent from a worker thread. A
        feed cancelled before the thread sent it drops it (counted in neither ``asks`` nor
        ``answered``); one already sent goes on in its thread and is counted when it returns."""
        dropped = False

        def send() -> CameraViewAnswer:
            with self._lock:
                if dropped:
                    raise RuntimeError("the camera feed stopped before this ask was sent")
                self.asks += 1
            try:
                return station.camera_view(WIDTH)
            finally:
                with self._lock:
                    self.answered += 1

        try:
            return await anyio.to_thread.run_sync(send)
        except BaseException:
            with self._lock:
                dropped = True
            raise


def _payload(answer: dict[str, Any]) -> dict[str, Any]:
    """The answer as the page uses it: each JPEG as a data URL."""
    cams = []
    for c in answer["cameras"]:
        b64 = c.pop("jpeg_base64")
        cams.append({**c, "src": f"data:image/jpeg;base64,{b64}" if b64 else None})
    return {**answer, "cameras": cams}


def feed_of(request: Request) -> CameraFeed:
    feed: CameraFeed | None = getattr(request.app.state, "web_cameras", None)
    if feed is None:
        feed = request.app.state.web_cameras = CameraFeed(request.app)
    return feed


#: the figures' explanations (term, what it says)
FIGURES = (
    (N_("Focus"), N_("The variance of the image's Laplacian (how strong its edges are) over the "
                     "recipe's mark windows, or over the whole image when the camera sees no "
                     "marks. It has no unit of its own: turn the focus ring slowly and stop "
                     "where the figure is highest (the peak is kept while the view is open). "
                     "Change nothing else meanwhile: more light or contrast also raises it.")),
    (N_("Mean"), N_("The mean grey level of the image, 0 (black) to 255 (white).")),
    (N_("Saturated"), N_("The share of pixels at 255. A mark whose edge is saturated cannot be "
                         "located to a fraction of a pixel: keep that share near zero on the part "
                         "(shiny spots aside).")),
    (N_("Dark"), N_("The share of pixels at 0: no signal there.")),
)


def figures_help() -> str:
    """The panel that says how to read the figures, in the page's language."""
    e = html.esc
    terms = "".join(f"<dt>{e(_(term))}</dt><dd>{e(_(what))}</dd>" for term, what in FIGURES)
    return ('<section class="panel camera-help"><h2>' + e(_("Reading the figures"))
            + f"</h2><dl>{terms}</dl><p>"
            + e(_("Frames are taken between triggers, at most twice a second, only while this "
                  "page is open; a trigger always comes first (a frame then says it is not "
                  "new).")) + "</p></section>")


@router.get("/cameras")
async def cameras_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    if not html.can(user, Role.OPERATOR):
        body = ('<section class="panel"><h2>' + html.esc(_("Operator role needed"))
                + "</h2><p>" + html.esc(_(
                    "The live camera view makes the station take frames; it needs the role "
                    "operator or above. You are logged in as {name} with role {role}.").format(
                        name=user.name, role=user.role.value)) + "</p></section>")
        return HTMLResponse(html.layout(_("Cameras"), user, body, "/cameras"), status_code=403)
    body = ('<div id="camera-view" data-events="/web/cameras/events" data-updates="0">\n'
            '<p id="camera-note" class="msg" role="status">'
            + html.esc(_("Connecting to the station…")) + "</p>\n"
            '<div id="camera-grid" class="camera-grid"></div></div>' + figures_help())
    return HTMLResponse(html.layout(_("Cameras"), user, body, "/cameras"))


@router.get("/web/cameras/events")
async def events(request: Request) -> StreamingResponse:
    await need(request, Role.OPERATOR)
    return StreamingResponse(feed_of(request).stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})
