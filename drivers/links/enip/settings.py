"""The EtherNet/IP backend's settings: the station file's ``links.enip`` block
(docs/ethernet-ip.md)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from .. import layout
from ..allowlist import networks
from ..handshake import HandshakeConfig
from ..layout import ByteOrder
from .admission import Limits
from .codec import Identity
from .objects import Assemblies

# No ODVA vendor id is assigned to mvpose: 0xFFFF marks that; an integrator with an id of their
# own sets vendor_id (and regenerates the EDS: `python -m drivers.links.enip.eds`).
UNASSIGNED_VENDOR = 0xFFFF
GENERIC_DEVICE = 0x2B  # device type "Generic Device (keyable)"


class EnipLinkConfig(BaseModel):
    """EtherNet/IP adapter for the line's scanner (docs/ethernet-ip.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0: every interface)")
    port: int = Field(44818, ge=0, le=65535,
                      description="TCP (and UDP ListIdentity) port; 0: any free port, tests")
    io_port: int = Field(2222, ge=0, le=65535,
                         description="UDP port of class 1 I/O; 0: any free port, tests")
    allowlist: tuple[str, ...] = Field(
        (), description="scanner addresses or networks allowed; empty = any host")
    min_rpi_ms: float = Field(2.0, ge=2.0, le=10_000, description="smallest RPI accepted")
    max_connections: int = Field(8, ge=1, le=64,
                                 description="class 1 + class 3 connections open at once")
    max_sessions: int = Field(16, ge=1, le=256, description="encapsulation sessions at once")
    vendor_id: int = Field(UNASSIGNED_VENDOR, ge=1, le=0xFFFF)
    product_code: int = Field(1, ge=1, le=0xFFFF)
    serial_number: int = Field(1, ge=0, le=0xFFFF_FFFF)
    product_name: str = Field("mvpose station", min_length=1, max_length=32, pattern=r"^[ -~]+$")
    watchdog_s: float = Field(1.0, ge=0, le=60, description="PLC heartbeat timeout; 0 = off")
    trigger_hold_s: float = Field(1.0, ge=0, le=60,
                                  description="TRIGGER high this long after the answer = error")
    measure_timeout_s: float | None = Field(
        None, gt=0, le=600,
        description="the link's own backstop; default: the station deadline + 2 s")

    @field_validator("allowlist")
    @classmethod
    def _networks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        networks(value)
        return value

    def identity(self) -> Identity:
        return Identity(self.vendor_id, GENERIC_DEVICE, self.product_code, REVISION,
                        self.serial_number, self.product_name)

    def limits(self) -> Limits:
        return Limits(max_sessions=self.max_sessions, max_connections=self.max_connections,
                      min_rpi_us=round(self.min_rpi_ms * 1000))

    def assemblies(self) -> Assemblies:
        """Input and output assemblies the size of the layout's blocks."""
        return Assemblies(input_size=layout.INPUT_SIZE, output_size=layout.OUTPUT_SIZE)

    def handshake(self, initial_recipe: int) -> HandshakeConfig:
        """The handshake's settings from this block: 32-bit values little-endian (CDAB)."""
        return HandshakeConfig(
            word_order=ByteOrder.LITTLE.word_order,
            measure_timeout_s=self.measure_timeout_s or 0.0,
            watchdog_s=self.watchdog_s,
            trigger_hold_s=self.trigger_hold_s,
            allowlist=tuple(self.allowlist),
            initial_recipe=initial_recipe,
        )


REVISION = (1, 1)  # the adapter's major.minor revision (Identity attribute 4, the EDS)
