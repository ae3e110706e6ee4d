"""The Modbus/TCP backend of the link seam: :class:`ModbusLink`, the PLC handshake's server
started with the station file's ``links.modbus`` settings.

Registers are the fieldbus layout's words; the handshake is shared with the other cyclic links
(drivers/links/handshake); Modbus framing and the register mirror stay inside this folder.
"""

from __future__ import annotations

from typing import Any

from .. import layout as r
from ..base import Link, StationHandler
from .server import PlcServer
from .settings import ModbusLinkConfig


class ModbusLink(Link):
    """Modbus/TCP server for the PLC."""

    name = "modbus"
    config: ModbusLinkConfig

    def __init__(self, config: ModbusLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: PlcServer | None = None

    async def start(self) -> None:
        cfg = self.config.handshake(self.handler.selected_recipe())
        server = PlcServer(self.handler, cfg, unit_id=self.config.unit_id)
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

    def line_state(self) -> str | None:
        return None if self.server is None else self.server.state.name

    def recipe_changed(self) -> None:
        if self.server is not None:
            self.server.recipe_selected(self.handler.selected_recipe(),
                                        self.handler.convention().code)

    def status(self) -> dict[str, Any]:
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
