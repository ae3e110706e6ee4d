"""The PROFINET backend's settings: the station file's ``links.profinet`` block
(docs/profinet.md)."""

from __future__ import annotations

import os

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..handshake import HandshakeConfig
from ..layout import ByteOrder
from .device import valid_station_name

# No PROFINET vendor id is assigned to mvpose: 0xFFFF marks that; an integrator with an id of
# their own sets vendor_id (and regenerates the GSDML: `python -m drivers.links.profinet.gsdml`).
UNASSIGNED_VENDOR = 0xFFFF


class ProfinetLinkConfig(BaseModel):
    """PROFINET IO-device for the line's IO-controller (docs/profinet.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    interface: str = Field("eth0", min_length=1, max_length=15,
                           description="network interface the device answers on")
    station_name: str = Field("mvpose-station", description="NameOfStation (DCP)")
    rpc_host: str = Field("0.0.0.0", description="address of the RPC socket (UDP 34964) until "
                          "the controller sets one by DCP")
    accept_ip_from_controller: bool = Field(
        True, description="a DCP Set IP sets the interface's address (permanent ones kept "
        "across restarts); false: refused (SET not possible by local reasons)")
    state_dir: str | None = Field(
        None, description="the device's permanent IP and I&M1..4 records; default "
        "<data_dir>/profinet (MVPOSE_DATA_DIR, else var)")
    rpc_port: int = Field(34964, ge=1, le=65535)
    vendor_id: int = Field(UNASSIGNED_VENDOR, ge=0, le=0xFFFF)
    device_id: int = Field(0x0001, ge=0, le=0xFFFF)
    order_id: str = Field("MVPOSE-PN", max_length=20, pattern=r"^[ -~]*$")
    serial: str = Field("1", max_length=16, pattern=r"^[ -~]*$")
    min_cycle_ms: float = Field(1.0, ge=1.0, le=512,
                                description="shortest send clock × reduction ratio accepted")
    input_phase_ms: float | None = Field(
        None, ge=0, le=256, description="the input frame leaves this long after the "
        "controller's output frame (at most half a cycle; default half a cycle): an answer "
        "ready by then goes with it")
    poll_s: float = Field(0.05, gt=0, le=0.05,
                          description="a backstop: the input image goes to the device as it "
                          "changes, and at least this often")
    realtime_priority: int = Field(
        10, ge=0, le=99, description="SCHED_FIFO priority of the device's process, so that "
        "the host's other work does not delay a cycle (0: normal scheduling; needs root or "
        "CAP_SYS_NICE, else the device runs with normal scheduling and its status says so)")
    watchdog_s: float = Field(1.0, ge=0, le=60, description="PLC heartbeat timeout; 0 = off")
    trigger_hold_s: float = Field(1.0, ge=0, le=60,
                                  description="TRIGGER high this long after the answer = error")
    measure_timeout_s: float | None = Field(
        None, gt=0, le=600,
        description="the link's own backstop; default: the station deadline + 2 s")

    @field_validator("station_name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not valid_station_name(value):
            raise ValueError("not a PROFINET NameOfStation: labels of a-z, 0-9 and '-', "
                             "1..63 characters each, 240 at most, not 'port-...'")
        return value

    def handshake(self, initial_recipe: int) -> HandshakeConfig:
        """The handshake's settings: every value big-endian (ABCD), as PROFINET carries it."""
        return HandshakeConfig(
            word_order=ByteOrder.BIG.word_order,
            measure_timeout_s=self.measure_timeout_s or 0.0,
            watchdog_s=self.watchdog_s,
            trigger_hold_s=self.trigger_hold_s,
            initial_recipe=initial_recipe,
        )

    def child(self) -> dict[str, object]:
        """What the device's process needs (JSON)."""
        state_dir = self.state_dir or os.path.join(os.environ.get("MVPOSE_DATA_DIR", "var"),
                                                   "profinet")
        return {**{k: getattr(self, k) for k in (
            "interface", "station_name", "rpc_host", "rpc_port", "vendor_id", "device_id",
            "order_id", "serial", "min_cycle_ms", "realtime_priority", "input_phase_ms",
            "accept_ip_from_controller")}, "state_dir": os.path.abspath(state_dir)}
