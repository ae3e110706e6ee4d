"""The adapter's CIP objects for explicit messages: Identity (0x01), Message Router (0x02),
Assembly (0x04), TCP/IP Interface (0xF5) and Ethernet Link (0xF6), as pure functions of a
request and the adapter's state (the Connection Manager lives in :mod:`.adapter`).

Attribute numbers and types follow "The CIP Networks Library" Vol 1, chapter 5 (5-2 Identity,
5-3 Message Router, 5-5 Assembly) and Vol 2, chapter 5 (5-3 TCP/IP Interface, 5-4 Ethernet Link).
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Callable
from dataclasses import dataclass

from .. import layout
from .cip import GeneralStatus, Request, Response, Service
from .codec import Identity

IDENTITY, MESSAGE_ROUTER, ASSEMBLY, CONNECTION_MANAGER = 0x01, 0x02, 0x04, 0x06
TCP_IP, ETHERNET_LINK = 0xF5, 0xF6
ASSEMBLY_DATA, ASSEMBLY_SIZE = 3, 4


@dataclass(frozen=True)
class Assemblies:
    """The assembly instances, each a view of the fieldbus layout (docs/ethernet-ip.md):
    input is the layout's INPUT block (T→O, produced), output its OUTPUT block (O→T, consumed),
    configuration holds nothing."""

    input_instance: int = 100
    output_instance: int = 150
    config_instance: int = 151
    input_size: int = layout.INPUT_SIZE
    output_size: int = layout.OUTPUT_SIZE


@dataclass(frozen=True)
class SetOutputs:
    """A Set_Attribute_Single on the output assembly's data: the PLC's new output image."""

    data: bytes


class ObjectModel:
    """Answers explicit requests to the objects above. ``inputs()`` gives the input image now;
    ``outputs()`` the output image now; ``owned()`` says whether a class 1 exclusive owner holds
    the output assembly (then a Set on it is an object state conflict, Vol 1, 5-5.4)."""

    def __init__(self, identity: Identity, assemblies: Assemblies, host: str,
                 inputs: Callable[[], bytes], outputs: Callable[[], bytes],
                 owned: Callable[[], bool]) -> None:
        self.identity = identity
        self.assemblies = assemblies
        self.host = host
        self.inputs = inputs
        self.outputs = outputs
        self.owned = owned

    def handle(self, req: Request) -> tuple[Response, SetOutputs | None]:
        """The response to ``req`` and, for an accepted Set on the output assembly, what it set."""
        cls, inst = req.path.class_id, req.path.instance
        if cls is None or inst is None:
            return Response(req.service, GeneralStatus.PATH_DESTINATION_UNKNOWN), None
        if cls == ASSEMBLY:
            return self._assembly(req, inst)
        table = {IDENTITY: self._identity, MESSAGE_ROUTER: self._router, TCP_IP: self._tcp_ip,
                 ETHERNET_LINK: self._ethernet_link}
        if cls not in table:
            return Response(req.service, GeneralStatus.PATH_DESTINATION_UNKNOWN), None
        attributes = table[cls](inst)
        if attributes is None:
            return Response(req.service, GeneralStatus.PATH_DESTINATION_UNKNOWN), None
        return _read_only(req, attributes), None

    # --------------------------------------------------------------------- objects

    def _identity(self, inst: int) -> dict[int, bytes] | None:
        if inst == 0:
            return {1: struct.pack("<H", 1), 2: struct.pack("<H", 1)}
        if inst != 1:
            return None
        all_ = self.identity.attributes_all()
        name = self.identity.product_name.encode("ascii")
        return {0: all_, 1: all_[0:2], 2: all_[2:4], 3: all_[4:6], 4: all_[6:8], 5: all_[8:10],
                6: all_[10:14], 7: bytes([len(name)]) + name}

    def _router(self, inst: int) -> dict[int, bytes] | None:
        if inst == 0:
            return {1: struct.pack("<H", 1)}
        if inst != 1:
            return None
        classes = (IDENTITY, MESSAGE_ROUTER, ASSEMBLY, CONNECTION_MANAGER, TCP_IP, ETHERNET_LINK)
        # attribute 1: the object list (count, then class codes); 2: connections supported
        return {1: struct.pack(f"<H{len(classes)}H", len(classes), *classes),
                2: struct.pack("<H", 8)}

    def _tcp_ip(self, inst: int) -> dict[int, bytes] | None:
        if inst == 0:
            return {1: struct.pack("<H", 4)}
        if inst != 1:
            return None
        ip = int(ipaddress.IPv4Address(self.host)) if _is_ipv4(self.host) else 0
        link_path = bytes([0x20, ETHERNET_LINK, 0x24, 0x01])
        host_name = b""
        return {
            1: struct.pack("<I", 1),  # status: configured from the host's own settings
            2: struct.pack("<I", 0),  # configuration capability: none settable through CIP
            3: struct.pack("<I", 0),  # configuration control: stored values
            4: struct.pack("<H", len(link_path) // 2) + link_path,
            5: struct.pack("<IIIIIH", ip, 0, 0, 0, 0, 0),  # address, mask, gateway, DNS, domain
            6: struct.pack("<H", len(host_name)) + host_name,
        }

    def _ethernet_link(self, inst: int) -> dict[int, bytes] | None:
        if inst == 0:
            return {1: struct.pack("<H", 4)}
        if inst != 1:
            return None
        # 100 Mbit/s; flags: link active, full duplex, speed and duplex negotiated (3 << 2)
        return {1: struct.pack("<I", 100), 2: struct.pack("<I", 0x0F), 3: bytes(6)}

    def _assembly(self, req: Request, inst: int) -> tuple[Response, SetOutputs | None]:
        a = self.assemblies
        if inst == 0:
            return _read_only(req, {1: struct.pack("<H", 2), 2: struct.pack("<H", 151)}), None
        images: dict[int, Callable[[], bytes]] = {
            a.input_instance: self.inputs, a.output_instance: self.outputs,
            a.config_instance: lambda: b"",
        }
        if inst not in images:
            return Response(req.service, GeneralStatus.OBJECT_DOES_NOT_EXIST), None
        if req.service == Service.SET_ATTRIBUTE_SINGLE and req.path.attribute == ASSEMBLY_DATA:
            if inst != a.output_instance:
                return Response(req.service, GeneralStatus.ATTRIBUTE_NOT_SETTABLE), None
            if self.owned():
                return Response(req.service, GeneralStatus.OBJECT_STATE_CONFLICT), None
            if len(req.data) < a.output_size:
                return Response(req.service, GeneralStatus.NOT_ENOUGH_DATA), None
            if len(req.data) > a.output_size:
                return Response(req.service, GeneralStatus.TOO_MUCH_DATA), None
            return Response(req.service), SetOutputs(req.data)
        data = images[inst]()
        attrs = {ASSEMBLY_DATA: data, ASSEMBLY_SIZE: struct.pack("<H", len(data))}
        return _read_only(req, attrs), None


def _read_only(req: Request, attributes: dict[int, bytes]) -> Response:
    """Get_Attribute_Single / Get_Attributes_All over ``attributes`` (0: the Get_All form);
    a Set on any of them is refused as not settable."""
    if req.service == Service.GET_ATTRIBUTE_SINGLE:
        attr = req.path.attribute
        if attr is None or attr == 0 or attr not in attributes:
            return Response(req.service, GeneralStatus.ATTRIBUTE_NOT_SUPPORTED)
        return Response(req.service, data=attributes[attr])
    if req.service == Service.GET_ATTRIBUTES_ALL:
        if 0 in attributes:
            return Response(req.service, data=attributes[0])
        return Response(req.service, data=b"".join(attributes[k] for k in sorted(attributes)))
    if req.service in (Service.SET_ATTRIBUTE_SINGLE, Service.SET_ATTRIBUTES_ALL):
        if req.path.attribute is not None and req.path.attribute not in attributes:
            return Response(req.service, GeneralStatus.ATTRIBUTE_NOT_SUPPORTED)
        return Response(req.service, GeneralStatus.ATTRIBUTE_NOT_SETTABLE)
    return Response(req.service, GeneralStatus.SERVICE_NOT_SUPPORTED)


def _is_ipv4(host: str) -> bool:
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        return False
    return True
