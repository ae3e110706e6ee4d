"""The station file's ``links:`` section: how the station talks to the line's controllers.

Every setting that the link docs (docs/plc-interface.md, docs/integration.md) call a station
setting lives here, so a deployed station is configured by its file; `mvpose serve` and
`mvpose station` may override single values from the command line or the environment
(docs/operations.md lists them in one table). Plain data: the drivers build their servers from it.
"""

from __future__ import annotations

import ipaddress
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ModbusLinkConfig(_Model):
    """Modbus/TCP server for the PLC handshake (docs/plc-interface.md)."""

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
        description="the link's own backstop; default: the station deadline + 1 s")

    @field_validator("allowlist")
    @classmethod
    def _networks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for entry in value:
            try:
                ipaddress.ip_network(entry, strict=False)
            except ValueError:
                raise ValueError(f"allowlist entry {entry!r} is not an address or network") \
                    from None
        return value


class LinksConfig(_Model):
    """Every link of the station; each backend has its own block."""

    modbus: ModbusLinkConfig = ModbusLinkConfig()
