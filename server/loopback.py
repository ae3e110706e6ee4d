"""The whole station on loopback: station + API on simulated cameras, and a PLC twin driving it.

Used by ``mvpose demo``, the end-to-end tests and the station benchmark, so all three run the same
production code paths: the FastAPI app with its lifespan (store, migrations, tokens), the
runtime's PLC link on loopback, and the twin talking to it like the PLC over the bus chosen
(Modbus/TCP by default; the buses are server/plc_buses.py's table).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import uvicorn

from drivers.links.layout import Status
from drivers.links.modbus.twin import modbus_twin
from drivers.links.twin import PlcPort, PlcStatus, PlcTwin
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, compose, from_robot, invert, to_robot, transform_error
from server.app import create_app
from server.links import load_station
from server.plc_buses import LOOPBACK_LINKS, Bus, open_bus
from server.settings import Settings
from server.station.client import StationClient
from server.station.core import Station, StationOptions
from server.station.process import StationProcess


@dataclass(frozen=True)
class TriggerRow:
    """One trigger as the PLC saw it, beside the truth the simulator knows."""

    trigger_id: int
    result_code: int
    true_offset: Array  # recipe convention values
    measured_offset: Array  # what the PLC read (PLC form), zeros when NOK
    rot_err_deg: float
    trans_err_mm: float
    sigma_mm: float
    sigma_deg: float
    server_ms: float  # the server's processing time, as published to the PLC
    roundtrip_ms: float  # trigger written → answer read by the twin


def true_offset(recipe: RecipeConfig, T_rf_from_pf: Array) -> Array:
    """The base-frame offset the station should report for a part at ``T_rf_from_pf``."""
    delta = compose(T_rf_from_pf, invert(recipe.T_rf_from_pf0.matrix))
    return to_robot(delta, recipe.robot_convention)


def offset_error(recipe: RecipeConfig, true: Array, measured: Array) -> tuple[float, float]:
    """(deg, mm) between two offsets, at the grasp point (where the robot uses it)."""
    conv = recipe.robot_convention
    G = compose(recipe.T_rf_from_pf0.matrix, recipe.T_pf_from_grasp.matrix)
    return transform_error(compose(from_robot(measured, conv), G),
                           compose(from_robot(true, conv), G))


async def move_part(runtime: Station, twin: PlcTwin, T_rf_from_pf: Array) -> None:
    """Render every simulated camera at the new part pose (in a thread; the PLC keeps beating)."""
    await asyncio.to_thread(runtime.scene.set_part_pose, T_rf_from_pf)


async def trigger(
    twin: PlcTwin, recipe: RecipeConfig, trigger_id: int, truth: Array | None, *,
    view_index: int = 0, part_id: str | None = None, timeout: float = 5.0,
) -> tuple[PlcStatus, TriggerRow | None]:
    """One PLC handshake; with the true part pose, the row comparing the answer to it."""
    t = time.perf_counter()
    status = await twin.cycle(trigger_id, view_index, part_id=part_id, timeout=timeout)
    roundtrip = (time.perf_counter() - t) * 1e3
    if truth is None or not status.has(Status.RESULT_VALID) and status.has(Status.VIEW_DONE):
        return status, None
    want = true_offset(recipe, truth)
    got = np.array(status.offset_float, dtype=float)
    if status.result_code == 0:
        deg, mm = offset_error(recipe, want, got)
    else:
        deg = mm = float("nan")
    s_um, s_rot = status.sigma_counts
    return status, TriggerRow(
        trigger_id=trigger_id, result_code=status.result_code, true_offset=want,
        measured_offset=got, rot_err_deg=deg, trans_err_mm=mm, sigma_mm=s_um / 1000.0,
        sigma_deg=s_rot / 1e4, server_ms=status.processing_ms, roundtrip_ms=roundtrip,
    )


@dataclass
class Loopback:
    runtime: Station
    twin: PlcTwin
    server: uvicorn.Server | None
    base_url: str | None
    bus: Bus | None = None


@dataclass
class RunningServer:
    runtime: Station
    server: uvicorn.Server | None
    base_url: str | None


def _twin(link: str, port: int, poll_s: float) -> PlcTwin:
    """The PLC twin on backend ``link``'s bus, for a link listening on ``port``."""
    if link == "enip":
        from drivers.links.enip.twin import enip_twin

        return enip_twin("127.0.0.1", port, poll_s=poll_s)
    return modbus_twin("127.0.0.1", port, poll_s=poll_s)


@contextlib.asynccontextmanager
async def running_server(
    settings: Settings, options: StationOptions | None = None, *,
    http_host: str = "127.0.0.1", http_port: int | None = 0, link: str = "modbus",
    links: dict[str, dict[str, Any]] | None = None,
) -> AsyncIterator[RunningServer]:
    """The station (with its control channel) + the API app served by uvicorn (unless
    ``http_port`` is None), in this process, with no PLC attached.

    `mvpose serve` runs the two as processes of their own; here they are threads of this one, so
    tests can reach into the station (its simulated scene, its store) while the API reaches it
    through the control channel exactly as in production. The station file is
    ``settings.station``; the Modbus link listens on a free loopback port. The PLC side is up to
    the caller: :func:`running_station` adds an in-process twin; the station benchmark runs
    `mvpose serve` and the twin as processes. ``link`` other than Modbus: that backend's link
    is on loopback too (free ports), and the Modbus link is off, so the station's state is
    the one that link's PLC sees. ``links``: blocks merged over all that (a bus's whose PLC
    the station connects to, such as S7's CPU: :mod:`server.plc_buses`).
    """
    if settings.station is None:
        raise ValueError("settings.station must name the station file")
    extra_links = links
    station = load_station(settings.station)
    links = dict(station.links)  # the PLC twin's link, on loopback
    links["modbus"] = {**(links.get("modbus") or {}), **LOOPBACK_LINKS["modbus"]}
    if link != "modbus":
        links[link] = {**(links.get(link) or {}), **LOOPBACK_LINKS[link]}
        links["modbus"]["enabled"] = False
    for name, block in (extra_links or {}).items():
        links[name] = {**(links.get(name) or {}), **block}
    station = station.model_copy(update={"links": links})
    proc = StationProcess(settings, station, options or StationOptions())
    await asyncio.to_thread(proc.start)
    try:
        if http_port is None:
            yield RunningServer(runtime=proc.station, server=None, base_url=None)
            return
        app = create_app(settings, StationClient(settings.resolved_control_socket))
        config = uvicorn.Config(app, host=http_host, port=http_port, log_level="warning",
                                lifespan="on", timeout_graceful_shutdown=3)
        server = uvicorn.Server(config)
        failed: list[str] = []
        thread = threading.Thread(target=_serve, args=(server, failed), name="http",
                                  daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + 60
            while not server.started:
                if not thread.is_alive():
                    why = "".join(failed) or "see the log"
                    raise RuntimeError(f"the API server failed to start ({why})")
                if time.monotonic() > deadline:
                    raise TimeoutError("the API server did not start within 60 s")
                await asyncio.sleep(0.02)
            sock = server.servers[0].sockets[0].getsockname()
            yield RunningServer(runtime=proc.station, server=server,
                                base_url=f"http://{sock[0]}:{sock[1]}")
        finally:
            server.should_exit = True
            await asyncio.to_thread(thread.join, 60)
    finally:
        await asyncio.to_thread(proc.stop)


async def attach_twin(port: int | PlcPort, poll_s: float = 0.001, link: str = "modbus"
                      ) -> tuple[PlcTwin, asyncio.Task[None]]:
    """A connected twin with its cyclic heartbeat running, trigger enabled, station READY;
    ``port``: the port the station's ``link`` listens on, or the twin's own port on a bus
    (S7's, on the CPU the station polls).

    An earlier PLC's disconnect may have left the station in ERROR (heartbeat watchdog): the
    twin resets it first, as a PLC program does after a restart.
    """
    twin = _twin(link, port, poll_s) if isinstance(port, int) else PlcTwin(port, poll_s=poll_s)
    await twin.connect()
    # The PLC's cyclic heartbeat, next to the handshakes (the client serialises requests).
    beat = asyncio.create_task(twin.keep_alive(0.1), name="plc-heartbeat")
    try:
        status = await twin.enable()
        if status.has(Status.ERROR):
            await twin.reset_error()
        await twin.wait_for(lambda s: s.has(Status.READY), 5.0, "READY")
    except BaseException:
        await detach_twin(twin, beat)
        raise
    return twin, beat


async def detach_twin(twin: PlcTwin, beat: asyncio.Task[None]) -> None:
    """Stop the heartbeat task and disconnect, bounded.

    The stop lets a heartbeat write in flight finish (a cancel in the middle of it would leave
    the server answering a closed connection, which pymodbus logs as an error with a dump of
    the last frames); only a heartbeat still running after that is cancelled.
    """
    twin.stop_keep_alive()
    await asyncio.wait({beat}, timeout=2.0)
    if not beat.done():
        beat.cancel()
        await asyncio.wait({beat}, timeout=2.0)
    if beat.done() and not beat.cancelled():
        beat.exception()  # retrieved: a failed heartbeat is not news at disconnect
    twin.close()


@contextlib.asynccontextmanager
async def running_station(
    settings: Settings, options: StationOptions | None = None, *,
    http_host: str = "127.0.0.1", http_port: int | None = 0, twin_poll_s: float = 0.001,
    link: str = "modbus", links: dict[str, dict[str, Any]] | None = None,
) -> AsyncIterator[Loopback]:
    """:func:`running_server` plus a connected, enabled PLC twin on ``link``'s bus in this
    process (a key of :data:`server.plc_buses.BUSES`); ``links``: settings merged over the
    bus's blocks (a test's watchdog)."""
    bus = open_bus(link)
    blocks = {name: {**block, **(links or {}).get(name, {})} for name, block in bus.links.items()}
    blocks.update({name: block for name, block in (links or {}).items() if name not in blocks})
    try:
        async with running_server(settings, options, http_host=http_host,
                                  http_port=http_port, links=blocks) as rs:
            # A PLC scans every few ms; a twin polling flat out in this process would only
            # compete with the pipeline for the GIL.
            twin, beat = await attach_twin(bus.port(rs.runtime), twin_poll_s)
            try:
                yield Loopback(runtime=rs.runtime, twin=twin, server=rs.server,
                               base_url=rs.base_url, bus=bus)
            finally:
                await detach_twin(twin, beat)
    finally:
        bus.close()


def _serve(server: uvicorn.Server, failed: list[str]) -> None:
    # uvicorn calls sys.exit() when the lifespan fails; here that ends this thread with a reason.
    try:
        server.run()
    except SystemExit as err:
        failed.append(f"exit {err.code}; see the log")
