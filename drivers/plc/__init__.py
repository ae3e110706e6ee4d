"""PLC link over Modbus/TCP: register map, codecs, handshake state machine, server and PLC twin."""

from .machine import Handshake, HandshakeStats
from .registers import Command, Control, ErrorCode, State, Status, WordOrder
from .seam import PlcConfig, PlcHandler, TriggerOutcome, TriggerRequest
from .server import PlcServer, PlcStats

__all__ = [
    "Command",
    "Control",
    "ErrorCode",
    "Handshake",
    "HandshakeStats",
    "PlcConfig",
    "PlcHandler",
    "PlcServer",
    "PlcStats",
    "State",
    "Status",
    "TriggerOutcome",
    "TriggerRequest",
    "WordOrder",
]
