"""The Modbus backend's settings: the station file's ``links.modbus`` block
(docs/plc-interface.md, "Settings"), and the handshake's own settings derived from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..allowlist import Allowlist, networks
from .registers import WordOrder


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


@dataclass(frozen=True)
class PlcConfig:
    """What the handshake and its server run with; times in seconds, 0 disables a watch.
    Built from :class:`ModbusLinkConfig` (:meth:`of`); tests build it directly."""

    word_order: WordOrder = WordOrder.ABCD
    measure_timeout_s: float = 2.0  # a slower measurement becomes Reason.TIMEOUT
    command_timeout_s: float = 5.0
    watchdog_s: float = 1.0  # PLC heartbeat must change within this time once seen
    trigger_hold_s: float = 1.0  # TRIGGER high this long after the answer → Error TRIGGER_HELD
    tick_s: float = 0.05  # server heartbeat and watch period
    allowlist: tuple[str, ...] = ()  # PLC addresses or networks ("10.1.2.0/24"); empty = any
    initial_recipe: int = 0  # selected through the handler at start when not 0
    peers: Allowlist = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "word_order", WordOrder(self.word_order))
        for name in ("measure_timeout_s", "command_timeout_s", "watchdog_s", "trigger_hold_s"):
            value = getattr(self, name)
            if not value >= 0:
                raise ValueError(f"PlcConfig.{name} must be >= 0 s, got {value!r}")
        if not self.tick_s > 0:
            raise ValueError(f"PlcConfig.tick_s must be > 0 s, got {self.tick_s!r}")
        if not 0 <= self.initial_recipe <= 0xFFFF:
            raise ValueError(
                f"PlcConfig.initial_recipe must be 0..65535, got {self.initial_recipe}"
            )
        try:
            peers = Allowlist(self.allowlist)
        except ValueError as err:
            raise ValueError(f"PlcConfig.allowlist: {err}") from None
        object.__setattr__(self, "peers", peers)

    @classmethod
    def of(cls, settings: ModbusLinkConfig, initial_recipe: int) -> PlcConfig:
        """The handshake's settings from the station file's ``links.modbus`` block."""
        return cls(
            word_order=WordOrder[settings.word_order],
            measure_timeout_s=settings.measure_timeout_s or 0.0,
            watchdog_s=settings.watchdog_s,
            trigger_hold_s=settings.trigger_hold_s,
            allowlist=tuple(settings.allowlist),
            initial_recipe=initial_recipe,
        )

    def allows(self, host: str) -> bool:
        """Whether a PLC at ``host`` may connect (:class:`~drivers.links.allowlist.Allowlist`)."""
        return self.peers.allows(host)
