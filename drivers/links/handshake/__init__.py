"""The PLC handshake over the fieldbus layout, shared by every cyclic link (Modbus, EtherNet/IP,
S7, PROFINET): :mod:`.machine` is the pure state machine, :mod:`.runner` runs its effects
against the station, :mod:`.config` holds their settings, :mod:`.link` is the base of the
backends built on them. docs/plc-interface.md explains the handshake; docs/fieldbus-layout.md
lists the bytes."""

from .config import HandshakeConfig
from .link import HandshakeLink
from .machine import Effect, Handshake, HandshakeStats, Measure, ResetPipeline, RunCommand
from .runner import HandshakeRunner, LinkStats

__all__ = [
    "Effect",
    "Handshake",
    "HandshakeConfig",
    "HandshakeLink",
    "HandshakeRunner",
    "HandshakeStats",
    "LinkStats",
    "Measure",
    "ResetPipeline",
    "RunCommand",
]
