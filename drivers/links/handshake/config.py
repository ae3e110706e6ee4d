"""What the handshake and the runner around it run with, whatever the bus."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..allowlist import Allowlist
from ..layout import WordOrder


@dataclass(frozen=True)
class HandshakeConfig:
    """Times in seconds, 0 disables a watch. Each backend builds it from its own settings
    model; tests build it directly."""

    word_order: WordOrder = WordOrder.ABCD
    measure_timeout_s: float = 2.0  # a slower measurement becomes Reason.TIMEOUT
    command_timeout_s: float = 5.0
    watchdog_s: float = 1.0  # PLC heartbeat must change within this time once seen
    trigger_hold_s: float = 1.0  # TRIGGER high this long after the answer → Error TRIGGER_HELD
    tick_s: float = 0.05  # device heartbeat and watch period
    allowlist: tuple[str, ...] = ()  # PLC addresses or networks ("10.1.2.0/24"); empty = any
    initial_recipe: int = 0  # selected through the handler at start when not 0
    peers: Allowlist = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "word_order", WordOrder(self.word_order))
        for name in ("measure_timeout_s", "command_timeout_s", "watchdog_s", "trigger_hold_s"):
            value = getattr(self, name)
            if not value >= 0:
                raise ValueError(f"HandshakeConfig.{name} must be >= 0 s, got {value!r}")
        if not self.tick_s > 0:
            raise ValueError(f"HandshakeConfig.tick_s must be > 0 s, got {self.tick_s!r}")
        if not 0 <= self.initial_recipe <= 0xFFFF:
            raise ValueError(
                f"HandshakeConfig.initial_recipe must be 0..65535, got {self.initial_recipe}"
            )
        try:
            peers = Allowlist(self.allowlist)
        except ValueError as err:
            raise ValueError(f"HandshakeConfig.allowlist: {err}") from None
        object.__setattr__(self, "peers", peers)

    def allows(self, host: str) -> bool:
        """Whether a PLC at ``host`` may connect (:class:`~drivers.links.allowlist.Allowlist`)."""
        return self.peers.allows(host)
