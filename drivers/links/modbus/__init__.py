"""The Modbus/TCP backend of the link seam: the PLC handshake (docs/plc-interface.md).

- :mod:`.registers`: the register map as data; :mod:`.codecs`: 32-bit values, text, scaled poses;
- :mod:`.machine`: the handshake as a state machine over register images (no sockets);
- :mod:`.transport`: Modbus/TCP framing; :mod:`.server`: pymodbus in the caller's loop;
- :mod:`.link`: :class:`ModbusLink`; :mod:`.settings`: the station file's ``links.modbus``;
- :mod:`.twin`: a PLC program on a Modbus client, for the tests, the demo and the benches.
"""

from .link import ModbusLink
from .machine import Handshake, HandshakeStats
from .registers import Command, Control, ErrorCode, State, Status, WordOrder
from .server import PlcServer, PlcStats
from .settings import ModbusLinkConfig, PlcConfig

__all__ = [
    "Command",
    "Control",
    "ErrorCode",
    "Handshake",
    "HandshakeStats",
    "ModbusLink",
    "ModbusLinkConfig",
    "PlcConfig",
    "PlcServer",
    "PlcStats",
    "State",
    "Status",
    "WordOrder",
]
