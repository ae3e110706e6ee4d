"""The Modbus/TCP backend of the link seam: the PLC handshake (docs/plc-interface.md) on
registers, the fieldbus layout's words (drivers/links/layout.py).

- :mod:`.transport`: Modbus/TCP framing; :mod:`.server`: pymodbus in the caller's loop, with the
  handshake runner behind it (drivers/links/handshake);
- :mod:`.link`: :class:`ModbusLink`; :mod:`.settings`: the station file's ``links.modbus``;
- :mod:`.twin`: the PLC twin's Modbus port, for the tests, the demo and the benches.
"""

from ..handshake import Handshake, HandshakeConfig, HandshakeStats
from ..layout import Command, Control, ErrorCode, State, Status, WordOrder
from .link import ModbusLink
from .server import PlcServer, PlcStats
from .settings import ModbusLinkConfig

__all__ = [
    "Command",
    "Control",
    "ErrorCode",
    "Handshake",
    "HandshakeConfig",
    "HandshakeStats",
    "ModbusLink",
    "ModbusLinkConfig",
    "PlcServer",
    "PlcStats",
    "State",
    "Status",
    "WordOrder",
]
