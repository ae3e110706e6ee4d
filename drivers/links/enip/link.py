"""The EtherNet/IP backend of the link seam: :class:`EnipLink`, the adapter on the station's
loop with the bus-agnostic handshake (:class:`~drivers.links.handshake.HandshakeRunner`) over
the layout's blocks: the output assembly is the layout's OUTPUT block, the input assembly its
INPUT block, every value little-endian (CIP's order).

A scanner that stops (its connection times out) leaves the handshake without heartbeats: the
station reports it as it reports a Modbus PLC that went away (the watchdog, ``line_state``).
A scanner that goes to idle (run/idle header 0) clears the outputs, so the handshake sees
TRIGGER_ENABLE drop.
"""

from __future__ import annotations

from typing import Any

from .. import layout as r
from ..base import StationHandler
from ..handshake import HandshakeLink, HandshakeRunner
from ..layout import ByteOrder
from .settings import EnipLinkConfig
from .transport import EnipServer


class EnipLink(HandshakeLink):
    """EtherNet/IP adapter for the line's scanner (PLC)."""

    name = "enip"
    config: EnipLinkConfig

    def __init__(self, config: EnipLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: EnipServer | None = None

    async def start(self) -> None:
        cfg = self.config
        runner = HandshakeRunner(self.handler, cfg.handshake(self.handler.selected_recipe()),
                                 link="enip")
        await runner.start()
        server = EnipServer(
            cfg.identity(), lambda: runner.input_image(ByteOrder.LITTLE),
            lambda data: runner.write_output(data, ByteOrder.LITTLE),
            cfg.assemblies(), cfg.limits(), tuple(cfg.allowlist))
        try:
            await server.start(cfg.host, cfg.port, cfg.io_port)
        except BaseException:
            await runner.stop()
            raise
        self.runner, self.server = runner, server

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.stop()
            self.server = None
        if self.runner is not None:
            await self.runner.stop()
            self.runner = None

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("the EtherNet/IP link is not started")
        return self.server.port

    @property
    def io_port(self) -> int:
        if self.server is None:
            raise RuntimeError("the EtherNet/IP link is not started")
        return self.server.io_port

    def ready(self) -> bool:
        return self.server is not None

    def status(self) -> dict[str, Any]:
        if self.server is None or self.runner is None or self.server.adapter is None:
            return {"running": False}
        st, hs = self.server.stats, self.runner.machine.stats
        image = self.runner.machine.image
        io = [{"peer": c.peer, "rpi_ms": c.request.t_o_rpi_us / 1000, "running": c.running}
              for c in self.server.adapter.io_connections()]
        return {
            "running": True, "port": self.server.port, "io_port": self.server.io_port,
            "state": self.runner.machine.state.name,
            "io_connections": io,
            "connections": len(self.server.adapter.connections),
            "sessions": st.sessions, "rejected_peers": st.rejected_peers,
            "refused": st.refused, "timeouts": st.timeouts,
            "handler_errors": self.runner.stats.handler_errors,
            "last_errors": [*st.last_errors, *self.runner.stats.last_errors][-5:],
            # ours counts up every tick; the PLC's is watched (ONLINE while it changes)
            "server_heartbeat": image[r.IR_HEARTBEAT],
            "plc_online": bool(image[r.IR_STATUS] & r.Status.ONLINE),
            "error_code": image[r.IR_ERROR_CODE],
            "result_id": self.runner.machine.result_id,
            "watchdog_trips": hs.watchdog_trips,
            "missed_triggers": hs.missed_triggers,
        }
