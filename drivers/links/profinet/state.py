"""What the IO-device holds and hands back: its counters (:class:`Stats`), the one IO AR with
its two IOCRs and its alarm CR (:class:`Ar`), and what one call of the device gives the
transport (:class:`Out`: frames, datagrams, events, a new output image).
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field

from . import blocks
from .alarms import AlarmCr
from .dcp import Event


@dataclass
class Stats:
    rpc_requests: int = 0
    frames_in: int = 0
    frames_out: int = 0
    malformed: int = 0
    connects: int = 0
    refused_connects: int = 0
    module_diffs: int = 0
    data_hold_expired: int = 0
    releases: int = 0
    send_errors: int = 0
    last_errors: list[str] = field(default_factory=list)


@dataclass
class Ar:
    """The one application relationship (IO AR) and its two IOCRs."""

    request: blocks.ArRequest
    controller_mac: bytes
    controller_addr: tuple[str, int]
    input_cr: blocks.IocrRequest
    output_cr: blocks.IocrRequest
    input_frame_id: int
    output_frame_id: int
    alarm: AlarmCr
    phase: str = "parameter"  # parameter → ready (ApplicationReady sent) → data
    next_send: float = 0.0
    cycle: int = 0
    last_output: float | None = None
    connected_at: float = 0.0
    app_ready_at: float = 0.0
    app_ready_tries: int = 0
    app_ready_activity: uuid.UUID = field(default_factory=uuid.uuid4)
    off_phase: int = 0  # output frames in a row that came off the input frames' phase
    realigned: int = 0

    @property
    def input_period_s(self) -> float:
        return self.input_cr.cycle_us / 1e6

    @property
    def hold_s(self) -> float:
        """The data hold time: DataHoldFactor × the output IOCR's cycle."""
        return self.output_cr.data_hold_factor * self.output_cr.cycle_us / 1e6


@dataclass
class Out:
    """What one call hands the transport: Ethernet frames, UDP datagrams (data, address),
    events, and a new output image when the controller's outputs changed."""

    frames: list[bytes] = field(default_factory=list)
    datagrams: list[tuple[bytes, tuple[str, int]]] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    output: bytes | None = None
    cyclic: bool = False  # ``frames`` holds this cycle's input frame
    im_changed: bool = False  # an I&M record was written: store ``Device.im``
