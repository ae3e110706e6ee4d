"""DCP, the Discovery and basic Configuration Protocol of the IO-device (IEC 61158-6-10,
"DCP"), sans-I/O: Identify (all and by name), Get, Set (NameOfStation, Signal, IP), and what
its answers say about the device (:class:`Identity`); and the controller's side of it: the
Identify and Set requests and what their responses say.
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from . import frames as fr

if TYPE_CHECKING:
    from .state import Out

ROLE_IO_DEVICE: Final = 0x01


@dataclass
class Event:
    """Something the station should know: ``kind`` is connected, running, released,
    data_hold_expired, aborted, diagnosis, name_set, ip_set, ip_refused, im_written, signal;
    ``text`` says it for the log."""

    kind: str
    text: str


@dataclass
class Identity:
    """What DCP and I&M0 tell about the device."""

    mac: bytes
    station_name: str
    ip: tuple[bytes, bytes, bytes] = (bytes(4), bytes(4), bytes(4))  # address, mask, gateway
    vendor_id: int = 0xFFFF
    device_id: int = 0x0001
    vendor_text: str = "mvpose station"
    order_id: str = "MVPOSE-PN"
    serial: str = "1"
    software: tuple[int, int, int] = (1, 0, 0)


def valid_station_name(name: str) -> bool:
    """NameOfStation rules (IEC 61158-6-10, DNS-like): 1..240 characters, labels of 1..63
    of a-z, 0-9 and '-', not starting or ending with '-', not of the form port-xyz."""
    if not 1 <= len(name) <= 240 or name.startswith("port-"):
        return False
    for label in name.split("."):
        if not 1 <= len(label) <= 63 or label[0] == "-" or label[-1] == "-":
            return False
        if any(c not in "abcdefghijklmnopqrstuvwxyz0123456789-" for c in label):
            return False
    return True


def ip_suite_error(addr: bytes, mask: bytes, gateway: bytes) -> str | None:
    """Why an IP suite (IEC 61158-6-10 "IPParameterValue") cannot be the device's, or None:
    a netmask that is not contiguous ones, an address that is 0.0.0.0, multicast, loopback,
    broadcast or its subnet's own network or broadcast address, a gateway outside the subnet
    (0.0.0.0 and the address itself say: no gateway)."""
    a, m, g = (ipaddress.IPv4Address(x) for x in (addr, mask, gateway))
    try:
        net = ipaddress.IPv4Network(f"{a}/{m}", strict=False)
    except ValueError:
        return f"netmask {m} is not contiguous"
    if int(m) == 0:
        return "netmask 0.0.0.0"
    if int(a) == 0 or a.is_multicast or a.is_loopback or a.is_reserved or \
            a == ipaddress.IPv4Address("255.255.255.255"):
        return f"address {a} cannot be a device's"
    if net.prefixlen <= 30 and a in (net.network_address, net.broadcast_address):
        return f"address {a} is the network or broadcast address of {net}"
    if int(g) != 0 and g != a and g not in net:
        return f"gateway {g} is outside the subnet {net}"
    return None


# ------------------------------------------------------------------ the controller's side

def identify_request(src: bytes, xid: int, station_name: str | None = None) -> bytes:
    """An Identify request to the DCP multicast address: by NameOfStation, or all."""
    block = (fr.DcpBlock(*fr.Opt.NAME_OF_STATION, station_name.encode("ascii"))
             if station_name is not None else fr.DcpBlock(*fr.Opt.ALL, b""))
    pdu = fr.Dcp(fr.FRAME_ID_DCP_IDENTIFY_REQ, fr.Service.IDENTIFY, fr.Service.REQUEST, xid,
                 1, (block,))
    return fr.Ethernet(fr.DCP_MULTICAST, src, fr.ETHERTYPE_PN, pdu.pack()).pack()


def set_request(src: bytes, dst: bytes, xid: int, key: tuple[int, int], value: bytes,
                permanent: bool = True) -> bytes:
    """A Set request of one block (BlockQualifier 1: permanent, 0: temporary), e.g.
    NameOfStation or IP_PARAMETER (address, mask, gateway)."""
    data = struct.pack(">H", 1 if permanent else 0) + value
    pdu = fr.Dcp(fr.FRAME_ID_DCP_GET_SET, fr.Service.SET, fr.Service.REQUEST, xid, 0,
                 (fr.DcpBlock(*key, data),))
    return fr.Ethernet(dst, src, fr.ETHERTYPE_PN, pdu.pack()).pack()


def found_device(eth: fr.Ethernet) -> Identity | None:
    """The device an Identify response describes (None: not an Identify response)."""
    pdu = fr.Dcp.unpack(eth.payload)
    if pdu.frame_id != fr.FRAME_ID_DCP_IDENTIFY_RES or pdu.service_type != fr.Service.SUCCESS:
        return None
    blocks = {b.key: b.data[2:] for b in pdu.blocks}  # after BlockInfo
    found = Identity(eth.src, blocks.get(fr.Opt.NAME_OF_STATION, b"").decode("ascii",
                                                                            "replace"))
    ip = blocks.get(fr.Opt.IP_PARAMETER, b"")
    if len(ip) >= 12:
        found.ip = (ip[0:4], ip[4:8], ip[8:12])
    ids = blocks.get(fr.Opt.DEVICE_ID, b"")
    if len(ids) >= 4:
        found.vendor_id, found.device_id = struct.unpack_from(">HH", ids, 0)
    found.vendor_text = blocks.get(fr.Opt.VENDOR, b"").decode("ascii", "replace")
    return found


def set_result(eth: fr.Ethernet, xid: int) -> int | None:
    """The BlockError a Set response with ``xid`` carries (None: not that response)."""
    pdu = fr.Dcp.unpack(eth.payload)
    if pdu.frame_id != fr.FRAME_ID_DCP_GET_SET or pdu.xid != xid or \
            pdu.service_id != fr.Service.SET or pdu.service_type == fr.Service.REQUEST:
        return None
    errors = [b.data[2] for b in pdu.blocks if b.key == fr.Opt.CONTROL_RESPONSE and
              len(b.data) >= 3]
    return max(errors, default=fr.BLOCK_OPTION_UNSUPPORTED)


@dataclass
class DcpResponder:
    """The device's DCP side over its :class:`Identity` (a Set of NameOfStation changes it).
    A Set IP is refused while ``accept_ip`` is false; otherwise ``set_ip`` (the transport's:
    address, mask, gateway, permanent) makes it take effect and says what went wrong, if
    anything; without it the identity alone changes (the sans-I/O tests)."""

    identity: Identity
    accept_ip: bool = True
    set_ip: Callable[[tuple[bytes, bytes, bytes], bool], str | None] | None = None
    requests: int = 0
    _ip_refusal_said: bool = False

    def _dcp_blocks(self) -> dict[tuple[int, int], bytes]:
        ident = self.identity
        options = [fr.Opt.IP_MAC, fr.Opt.IP_PARAMETER, fr.Opt.VENDOR, fr.Opt.NAME_OF_STATION,
                   fr.Opt.DEVICE_ID, fr.Opt.DEVICE_ROLE, fr.Opt.DEVICE_OPTIONS,
                   fr.Opt.CONTROL_SIGNAL]
        return {
            fr.Opt.VENDOR: ident.vendor_text.encode("ascii"),
            fr.Opt.NAME_OF_STATION: ident.station_name.encode("ascii"),
            fr.Opt.DEVICE_ID: struct.pack(">HH", ident.vendor_id, ident.device_id),
            fr.Opt.DEVICE_ROLE: bytes([ROLE_IO_DEVICE, 0]),
            fr.Opt.DEVICE_OPTIONS: b"".join(bytes(o) for o in options),
            fr.Opt.IP_MAC: ident.mac,
            fr.Opt.IP_PARAMETER: b"".join(ident.ip),
        }

    def _answer_block(self, key: tuple[int, int]) -> fr.DcpBlock | None:
        value = self._dcp_blocks().get(key)
        if value is None:
            return None
        info = 0x0001 if key == fr.Opt.IP_PARAMETER and any(self.identity.ip[0]) else 0
        return fr.DcpBlock(key[0], key[1], struct.pack(">H", info) + value)

    def handle(self, eth: fr.Ethernet, ar_open: bool, out: Out) -> None:
        """One DCP request: its answer (if any) and events into ``out``."""
        pdu = fr.Dcp.unpack(eth.payload)
        if pdu.service_type != fr.Service.REQUEST:
            return
        self.requests += 1
        if pdu.service_id == fr.Service.IDENTIFY:
            if not all(self._matches(b) for b in pdu.blocks):
                return
            keys = [fr.Opt.NAME_OF_STATION, fr.Opt.VENDOR, fr.Opt.DEVICE_ID,
                    fr.Opt.DEVICE_ROLE, fr.Opt.DEVICE_OPTIONS, fr.Opt.IP_PARAMETER]
            blocks = tuple(b for k in keys if (b := self._answer_block(k)) is not None)
            reply = fr.Dcp(fr.FRAME_ID_DCP_IDENTIFY_RES, pdu.service_id, fr.Service.SUCCESS,
                           pdu.xid, 0, blocks)
        elif pdu.service_id == fr.Service.GET:
            # a Get request names one (option, suboption) per block, without data
            blocks = tuple(self._answer_block(b.key) or fr.DcpBlock(
                *fr.Opt.CONTROL_RESPONSE, bytes([*b.key, fr.BLOCK_SUBOPTION_UNSUPPORTED]))
                for b in pdu.blocks)
            reply = fr.Dcp(fr.FRAME_ID_DCP_GET_SET, pdu.service_id, fr.Service.SUCCESS,
                           pdu.xid, 0, blocks)
        elif pdu.service_id == fr.Service.SET:
            blocks = tuple(fr.DcpBlock(*fr.Opt.CONTROL_RESPONSE,
                                       bytes([*b.key, self._set(b, ar_open, out)]))
                           for b in pdu.blocks)
            reply = fr.Dcp(fr.FRAME_ID_DCP_GET_SET, pdu.service_id, fr.Service.SUCCESS,
                           pdu.xid, 0, blocks)
        else:
            reply = fr.Dcp(fr.FRAME_ID_DCP_GET_SET, pdu.service_id, fr.Service.UNSUPPORTED,
                           pdu.xid, 0, ())
        out.frames.append(fr.Ethernet(eth.src, self.identity.mac, fr.ETHERTYPE_PN,
                                      reply.pack()).pack())

    def _matches(self, b: fr.DcpBlock) -> bool:
        if b.key == fr.Opt.ALL:
            return True
        value = self._dcp_blocks().get(b.key)
        return value is not None and value == b.data

    def _set(self, b: fr.DcpBlock, ar_open: bool, out: Out) -> int:
        """One Set block (BlockQualifier then value); the BlockError it gets."""
        value = b.data[2:]
        if b.key == fr.Opt.NAME_OF_STATION:
            name = value.rstrip(b"\0").decode("ascii", "replace")
            if not valid_station_name(name):
                return fr.BLOCK_SET_NOT_POSSIBLE
            if ar_open:
                return fr.BLOCK_SET_NOT_POSSIBLE  # not while an AR is open
            self.identity.station_name = name
            out.events.append(Event("name_set", f"NameOfStation set to {name!r} by DCP"))
            return fr.BLOCK_OK
        if b.key == fr.Opt.CONTROL_SIGNAL:
            out.events.append(Event("signal", "DCP Signal: flash the station's indicator"))
            return fr.BLOCK_OK
        if b.key in (fr.Opt.CONTROL_START, fr.Opt.CONTROL_STOP):
            return fr.BLOCK_OK
        if b.key == fr.Opt.IP_PARAMETER:
            return self._set_ip(b.data, ar_open, out)
        if b.key[0] in (1, 2, 5):
            return fr.BLOCK_SUBOPTION_UNSUPPORTED
        return fr.BLOCK_OPTION_UNSUPPORTED

    def _set_ip(self, data: bytes, ar_open: bool, out: Out) -> int:
        """Set IP (BlockQualifier bit 0: permanent, else temporary; then address, netmask,
        gateway): its BlockError."""
        if len(data) != 14:
            return fr.BLOCK_SUBOPTION_NOT_SET
        permanent = bool(data[1] & 1)
        suite = (data[2:6], data[6:10], data[10:14])
        if not self.accept_ip:
            if not self._ip_refusal_said:
                self._ip_refusal_said = True
                out.events.append(Event("ip_refused", "DCP Set IP refused: the station's "
                                        "accept_ip_from_controller is false (said once)"))
            return fr.BLOCK_SET_NOT_POSSIBLE
        why = ip_suite_error(*suite)
        if why is not None:
            out.events.append(Event("ip_refused", f"DCP Set IP refused: {why}"))
            return fr.BLOCK_SUBOPTION_NOT_SET
        if suite == self.identity.ip and self.set_ip is None:
            return fr.BLOCK_OK
        if ar_open and suite[0] != self.identity.ip[0]:
            return fr.BLOCK_IN_OPERATION  # the AR's RPC endpoint is the address
        if self.set_ip is not None:
            failed = self.set_ip(suite, permanent)
            if failed is not None:
                out.events.append(Event("ip_refused", f"DCP Set IP failed: {failed}"))
                return fr.BLOCK_RESOURCE_ERROR
        self.identity.ip = suite
        addr, mask, gw = (str(ipaddress.IPv4Address(x)) for x in suite)
        out.events.append(Event("ip_set", f"IP set to {addr} mask {mask} gateway {gw} by DCP ("
                                + ("permanent" if permanent else "temporary") + ")"))
        return fr.BLOCK_OK
