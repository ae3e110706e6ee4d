"""The Modbus backend's settings: the station file's ``links.modbus`` block
(docs/modbus.md, "Settings"), and the handshake's settings derived from it."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..allowlist import networks
from ..handshake import HandshakeConfig
from ..layout import WordOrder


class ModbusLinkConfig(BaseModel):
    """Modbus/TCP server for the PLC handshake (docs/plc-interface.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0: every interface)")
    port: int = Field(502, ge=0, le=65535, description="TCP port (0: any free port, tests)")
    unit_id: int = Field(0, ge=0, le=255, description="Modbus unit id answered; 0 = any")
    word_order: Literal["ABCD", "CDAB"] = "ABCD"
    allowlist: tuple[str, ...] = Field(
        (), description="PLC addresses or networks allowed to connect; empty = any host")
    watchdog_s: float = Field(1.0, ge=0, le=60, description="PLC heartbeat timeout; 0 = off")
    trigger_hold_s: float = Field(1.0, ge=0, le=60,
                                  description="TRIGGER high this long after the answer = error")
    measure_timeout_s: float | None = Field(
        None, gt=0, le=600,
        description="the link's own backstop; default: the station deadline + 2 s, a second "
                    "behind the station's own watchdog")

    @field_validator("allowlist")
    @classmethod
    def _networks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        networks(value)
        return value

    def handshake(self, initial_recipe: int) -> HandshakeConfig:
        """The handshake's settings from this block."""
        return HandshakeConfig(
            word_order=WordOrder[self.word_order],
            measure_timeout_s=self.measure_timeout_s or 0.0,
            watchdog_s=self.watchdog_s,
            trigger_hold_s=self.trigger_hold_s,
            allowlist=tuple(self.allowlist),
            initial_recipe=initial_recipe,
        )
