"""The Modbus/TCP backend of the link seam: the PLC handshake of :mod:`drivers.plc`.

This adapter is where the station's terms meet the register map's: flange poses arrive in the
PLC form (``codecs.plc_to_pose``), offsets leave in it (``codecs.pose_to_plc``), the result id is
the record's seq. Everything else of the wire format (registers, word order, scaling, the state
machine) stays inside drivers/plc.
"""

from __future__ import annotations

import asyncio
from typing import Any

from drivers.plc import codecs
from drivers.plc.registers import WordOrder
from drivers.plc.seam import PlcConfig, TriggerOutcome, TriggerRequest
from drivers.plc.server import PlcServer
from mvpose_core.linkconfig import ModbusLinkConfig

from .base import Link, LinkOutcome, LinkRequest, StationHandler, relay


def plc_config(config: ModbusLinkConfig, initial_recipe: int) -> PlcConfig:
    """The handshake's settings from the station file's ``links.modbus`` block."""
    return PlcConfig(
        word_order=WordOrder[config.word_order],
        measure_timeout_s=config.measure_timeout_s or 0.0,
        watchdog_s=config.watchdog_s,
        trigger_hold_s=config.trigger_hold_s,
        allowlist=tuple(config.allowlist),
        initial_recipe=initial_recipe,
    )


class ModbusLink(Link):
    """Modbus/TCP server for the PLC; the handler of its handshake."""

    name = "modbus"
    config: ModbusLinkConfig

    def __init__(self, config: ModbusLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: PlcServer | None = None

    async def start(self) -> None:
        cfg = plc_config(self.config, self.handler.selected_recipe())
        server = PlcServer(_Adapter(self.handler), cfg, unit_id=self.config.unit_id)
        await server.start(self.config.host, self.config.port)
        self.server = server

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.stop()
            self.server = None

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("the Modbus link is not started")
        return self.server.port

    def ready(self) -> bool:
        return self.server is not None

    def recipe_changed(self) -> None:
        if self.server is not None:
            self.server.recipe_selected(self.handler.selected_recipe(),
                                        self.handler.convention().code)

    def status(self) -> dict[str, Any]:
        from drivers.plc import registers as r

        if self.server is None:
            return {"running": False}
        st = self.server.stats
        image = self.server.input_registers()
        return {
            "running": True, "port": self.server.port, "state": self.server.state.name,
            "connections": st.connections, "rejected_connections": st.rejected_connections,
            "timeouts": st.timeouts, "handler_errors": st.handler_errors,
            "last_errors": list(st.last_errors[-5:]),
            # ours counts up every tick; the PLC's is watched (ONLINE while it changes)
            "server_heartbeat": image[r.IR_HEARTBEAT],
            "plc_online": bool(image[r.IR_STATUS] & r.Status.ONLINE),
            "error_code": image[r.IR_ERROR_CODE],
            "result_id": self.server.machine.result_id,
            "watchdog_trips": st.handshake.watchdog_trips,
            "missed_triggers": st.handshake.missed_triggers,
        }


class _Adapter:
    """drivers.plc's PlcHandler in the station's terms (PLC form in, PLC form out)."""

    def __init__(self, station: StationHandler) -> None:
        self.station = station

    def _request(self, req: TriggerRequest) -> LinkRequest:
        pose = None
        if req.robot_pose is not None:
            pose = codecs.plc_to_pose(req.robot_pose, self.station.convention())
        return LinkRequest(link="modbus", trigger_id=req.trigger_id, view_index=req.view_index,
                           robot_pose=pose, part_id=req.part_id, recipe=req.recipe)

    def measure(self, request: TriggerRequest) -> asyncio.Future[TriggerOutcome]:
        conv = self.station.convention()
        pending = asyncio.ensure_future(self.station.measure(self._request(request)))
        done: asyncio.Future[TriggerOutcome] = asyncio.get_running_loop().create_future()
        relay(pending, done, lambda out: self._outcome(out, conv))
        done.add_done_callback(lambda f: pending.cancel() if f.cancelled() else None)
        return done

    @staticmethod
    def _outcome(out: LinkOutcome, conv: Any) -> TriggerOutcome:
        offset: tuple[float, ...] = (0.0,) * 6
        if out.result_code == 0 and out.offset is not None:
            offset = codecs.pose_to_plc(out.offset, conv)
        return TriggerOutcome(
            result_code=out.result_code, offset=offset, sigma_trans_mm=out.sigma_trans_mm,
            sigma_rot_deg=out.sigma_rot_deg, processing_ms=out.processing_ms,
            views_done=out.views_done, final=out.final,
            result_id=out.result_id if out.final or out.result_code else None)

    async def record_failure(self, request: TriggerRequest, code: int, message: str,
                             processing_ms: float) -> int:
        return await self.station.record_failure(self._request(request), code, message,
                                                 processing_ms)

    async def select_recipe(self, recipe: int) -> int:
        return await self.station.select_recipe(recipe)

    async def teach_reference(self) -> int:
        return await self.station.teach_reference("plc")

    async def reset(self) -> None:
        await self.station.reset()

    def convention_code(self) -> int:
        return self.station.convention().code
