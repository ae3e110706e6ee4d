"""The seam between PLC link and measurement pipeline: request, outcome, handler, settings."""

from __future__ import annotations

import ipaddress
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Protocol

from .registers import WordOrder


@dataclass(frozen=True)
class TriggerRequest:
    """One accepted trigger, as the PLC wrote it."""

    trigger_id: int  # u32 chosen by the PLC, echoed back with the result
    view_index: int  # 0 = fixed station, all cameras; 1..n = view of a robot-mounted rig
    robot_pose: tuple[float, ...] | None  # 6-value PLC form (see codecs.pose_to_plc) or None
    part_id: str  # VIN or data-matrix code, up to 40 ASCII characters
    recipe: int  # recipe selected when the trigger came


@dataclass(frozen=True)
class TriggerOutcome:
    """What the pipeline answers for one trigger.

    ``offset`` holds the 6 values of the PLC form in the recipe's robot convention
    (``codecs.pose_to_plc``: ABB's quaternion drops q1; ABB's full 7 values are accepted too).
    ``final`` is False for an intermediate view of a robot-mounted rig: the PLC then gets
    VIEW_DONE instead of a result. A NOK ``result_code`` always ends the sequence with a result
    whose offset is sent as zero.
    """

    result_code: int  # 0 = OK, 1..999 = the pipeline's NOK reason
    offset: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    sigma_trans_mm: float = 0.0
    sigma_rot_deg: float = 0.0
    processing_ms: float = 0.0
    views_done: int = 1
    final: bool = True
    # The record's seq (the durable result id published in input registers 8-9); None: the
    # handshake numbers results itself (a handler without a store, e.g. the tests' handlers).
    result_id: int | None = None


class PlcHandler(Protocol):
    """What the server plugs into the PLC link. Every call may be slow or raise."""

    def measure(self, request: TriggerRequest) -> Awaitable[TriggerOutcome]:
        """The measurement of one accepted trigger (an ``async def`` is fine).

        Called the moment the TRIGGER write is taken, before the PLC gets the write's response;
        a handler may start its work in the call itself and return a future. The link bounds the
        wait by ``PlcConfig.measure_timeout_s`` and cancels the awaitable then.
        """
        ...

    async def select_recipe(self, recipe: int) -> int:
        """Return 0 when the recipe is now active, else a NOK code (1..999)."""
        ...

    async def teach_reference(self) -> int:
        """Return 0 when the next final result will be taken as the zero offset."""
        ...

    async def reset(self) -> None:
        """Drop a half-done multi-view sequence (after ERROR_RESET or command RESET)."""
        ...

    def convention_code(self) -> int:
        """RobotConvention.code of the active recipe (register 44)."""
        ...


class RecordingHandler(PlcHandler, Protocol):
    """A handler that also records the answers the link gives on its own."""

    async def record_failure(self, request: TriggerRequest, code: int, message: str,
                             processing_ms: float) -> int:
        """Record a TIMEOUT or HANDLER_FAILED answer; returns its result id (0: not recorded)."""
        ...


@dataclass(frozen=True)
class PlcConfig:
    """Settings of the PLC link; times in seconds, 0 disables a watch."""

    word_order: WordOrder = WordOrder.ABCD
    measure_timeout_s: float = 2.0  # a slower measurement becomes Reason.TIMEOUT
    command_timeout_s: float = 5.0
    watchdog_s: float = 1.0  # PLC heartbeat must change within this time once seen
    trigger_hold_s: float = 1.0  # TRIGGER high this long after the answer → Error TRIGGER_HELD
    tick_s: float = 0.05  # server heartbeat and watch period
    allowlist: tuple[str, ...] = ()  # PLC addresses or networks ("10.1.2.0/24"); empty = any
    initial_recipe: int = 0  # selected through the handler at start when not 0
    _networks: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...] = field(
        default=(), init=False, repr=False, compare=False
    )

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
        nets = []
        for entry in self.allowlist:
            try:
                nets.append(ipaddress.ip_network(entry, strict=False))
            except ValueError as err:
                raise ValueError(f"PlcConfig.allowlist: {entry!r} is not an address") from err
        object.__setattr__(self, "_networks", tuple(nets))

    def allows(self, host: str) -> bool:
        """Whether a peer address may talk to the server."""
        if not self._networks:
            return True
        try:
            addr = ipaddress.ip_address(host)
        except ValueError:
            return False
        if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
            addr = addr.ipv4_mapped
        return any(addr in net for net in self._networks)
