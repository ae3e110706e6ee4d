"""How the PLC twin reaches a station over each fieldbus, for ``mvpose demo --link``, the tests
and the benches: one small table, ``BUSES``, of bus name → a factory of :class:`Bus`.

A bus gives the station file's ``links`` blocks it needs (merged over the file's own, on
loopback) and, once the station runs, the twin's :class:`~drivers.links.twin.PlcPort`. Where the
station is the server (Modbus/TCP, EtherNet/IP) the port connects to the station's link; where
it is the client (S7) the bus first starts the PLC's CPU (python-snap7's server with the two
DBs) that the station's link connects to; for PROFINET (the station is the IO-device) it makes
a veth pair with the controller's end in a network namespace, and the port is our own
IO-controller there (root needed; the bus says so otherwise).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the command line reads BUSES without importing the station
    from drivers.links.twin import PlcPort
    from server.station.core import Station


@dataclass
class Bus:
    """One fieldbus between the twin and the station."""

    name: str
    links: dict[str, dict[str, Any]]  # station file link blocks, merged over the file's own
    port: Callable[[Station], PlcPort]  # the twin's port, once the station runs
    describe: Callable[[Station], str]  # one line for the demo: where the PLC talks
    close: Callable[[], None] = field(default=lambda: None)


#: the block a listening backend's link gets on loopback (free ports)
LOOPBACK_LINKS: dict[str, dict[str, Any]] = {
    "modbus": {"host": "127.0.0.1", "port": 0},
    "enip": {"host": "127.0.0.1", "port": 0, "io_port": 0},
}


def _modbus() -> Bus:
    from drivers.links.modbus.twin import ModbusPort

    return Bus(
        "modbus", {"modbus": LOOPBACK_LINKS["modbus"]},
        lambda st: ModbusPort("127.0.0.1", st.link_port("modbus")),
        lambda st: f"Modbus    127.0.0.1:{st.link_port('modbus')}")


def _enip() -> Bus:
    from drivers.links.enip.twin import EnipPort

    # the station's Modbus link is off: the station's state is the EtherNet/IP handshake's
    return Bus(
        "enip", {"enip": LOOPBACK_LINKS["enip"], "modbus": {"enabled": False}},
        lambda st: EnipPort("127.0.0.1", st.link_port("enip")),
        lambda st: f"EtherNet/IP 127.0.0.1:{st.link_port('enip')}")


def _s7() -> Bus:
    from drivers.links.s7.twin import S7Cpu, S7Port

    cpu = S7Cpu().start()
    # the station's Modbus link is off: the station's state is the S7 handshake's
    return Bus(
        "s7", {"s7": cpu.settings, "modbus": {"enabled": False}},
        lambda _st: S7Port(cpu),
        lambda _st: (f"S7        PLC 127.0.0.1:{cpu.port} (python-snap7's server), trigger "
                     f"DB{cpu.trigger_db}, result DB{cpu.result_db}, polled every 5 ms"),
        cpu.stop)


def _profinet() -> Bus:
    from drivers.links.profinet.netns import VethLine, why_not
    from drivers.links.profinet.twin import ProfinetPort

    why = why_not()
    if why is not None:
        raise ValueError(f"--link profinet: {why}")
    name = "mvpose-demo"
    line = VethLine.create()
    # the station's Modbus link is off: the station's state is the PROFINET handshake's
    return Bus(
        "profinet", {"profinet": {"interface": line.device_if, "station_name": name,
                                  "rpc_host": line.device_ip},
                     "modbus": {"enabled": False}},
        lambda _st: ProfinetPort(line.controller_if, name, netns=line.ns),
        lambda _st: (f"PROFINET  device {name!r} on {line.device_if} ({line.device_ip}); the "
                     f"PLC twin's IO-controller on {line.controller_if} ({line.controller_ip}) "
                     f"in namespace {line.ns}, RT_CLASS_1 every 4 ms"),
        line.remove)


#: bus name → a factory of the bus (each starts what the twin needs: on loopback, or for
#: PROFINET a veth pair and a network namespace of its own)
BUSES: dict[str, Callable[[], Bus]] = {
    "modbus": _modbus,
    "enip": _enip,
    "s7": _s7,
    "profinet": _profinet,
}


def open_bus(name: str) -> Bus:
    """The bus ``name`` (a key of BUSES), started; ``close()`` it after the station stops."""
    try:
        factory = BUSES[name]
    except KeyError:
        raise ValueError(f"unknown PLC link {name!r}; known: {', '.join(BUSES)}") from None
    return factory()
