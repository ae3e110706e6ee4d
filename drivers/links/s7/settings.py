"""The S7 backend's settings: the station file's ``links.s7`` block (docs/s7.md).

mvpose is the S7 client here: it connects to the PLC, so there is no allowlist (the link talks to
the one PLC it is configured with and serves no one else).
"""

from __future__ import annotations

from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator


class S7LinkConfig(BaseModel):
    """mvpose as an S7 client (PUT/GET) of one PLC: it polls the trigger DB (the layout's
    output block, written by the PLC program) and writes the result DB (its input block)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    host: str = Field(description="the PLC's address (its PROFINET interface)")
    port: int = Field(102, ge=1, le=65535, description="ISO-on-TCP port (RFC 1006): 102")
    rack: int = Field(0, ge=0, le=7, description="the CPU's rack (0 on S7-1200/1500)")
    slot: int = Field(1, ge=0, le=31,
                      description="the CPU's slot: 1 on S7-1200/1500, 2 on most S7-300")
    local_tsap: int | None = Field(
        None, ge=0, le=0xFFFF,
        description="our TSAP instead of 0x0100 (with remote_tsap, for a CP or a LOGO!)")
    remote_tsap: int | None = Field(
        None, ge=0, le=0xFFFF,
        description="the PLC's TSAP instead of the one rack and slot give (0x0100 | rack << 5 "
                    "| slot): with it, rack and slot are not used")
    trigger_db: int = Field(100, ge=1, le=65535,
                            description="the DB the PLC writes (the trigger block, 80 bytes)")
    trigger_start: int = Field(0, ge=0, le=65535, description="its first byte in that DB")
    result_db: int = Field(101, ge=1, le=65535,
                           description="the DB mvpose writes (the result block, 168 bytes)")
    result_start: int = Field(0, ge=0, le=65535, description="its first byte in that DB")
    poll_s: float = Field(0.005, ge=0.001, le=1.0,
                          description="the trigger DB is read this often")
    request_timeout_s: float = Field(
        1.0, gt=0, le=60, description="a read or write unanswered this long: the PLC is lost")
    watchdog_s: float = Field(1.0, ge=0, le=60,
                              description="PLC heartbeat timeout; 0 = off")
    trigger_hold_s: float = Field(1.0, ge=0, le=60,
                                  description="TRIGGER high this long after the answer = error")
    measure_timeout_s: float | None = Field(
        None, gt=0, le=600,
        description="the link's own backstop; default: the station deadline + 2 s, a second "
                    "behind the station's own watchdog")
    reconnect_min_s: float = Field(0.1, gt=0, le=60,
                                   description="the first wait before connecting again")
    reconnect_max_s: float = Field(5.0, gt=0, le=600,
                                   description="the wait doubles up to this")

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if (self.local_tsap is None) != (self.remote_tsap is None):
            raise ValueError("local_tsap and remote_tsap go together (or neither: rack/slot)")
        if self.remote_tsap is not None and {"rack", "slot"} & self.model_fields_set:
            raise ValueError("give either rack/slot or local_tsap/remote_tsap, not both")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError(f"reconnect_max_s ({self.reconnect_max_s}) is below "
                             f"reconnect_min_s ({self.reconnect_min_s})")
        if self.trigger_db == self.result_db:
            from ..layout import INPUT_SIZE, OUTPUT_SIZE

            a = (self.trigger_start, self.trigger_start + OUTPUT_SIZE)
            b = (self.result_start, self.result_start + INPUT_SIZE)
            if a[0] < b[1] and b[0] < a[1]:
                raise ValueError(
                    f"the trigger block (DB{self.trigger_db} bytes {a[0]}..{a[1] - 1}) overlaps "
                    f"the result block (bytes {b[0]}..{b[1] - 1}) in the same DB")
        return self

    @property
    def tsaps(self) -> tuple[int, int]:
        """(local, remote) TSAP: as given, or a PG connection to rack/slot."""
        if self.local_tsap is not None and self.remote_tsap is not None:
            return self.local_tsap, self.remote_tsap
        return 0x0100, 0x0100 | (self.rack << 5) | self.slot
