"""Whether the adapter accepts a Forward Open, as a pure function of the request and the
connection table: the Connection Manager's checks (Vol 1, 3-5.5.2) in the order a target makes
them, each refusal with its extended status (Vol 1, table 3-5.33) and the words that follow it.
"""

from __future__ import annotations

from dataclasses import dataclass

from .cip import ExtendedStatus, ForwardOpen
from .codec import Identity
from .objects import ASSEMBLY, MESSAGE_ROUTER, Assemblies


@dataclass(frozen=True)
class Limits:
    """What the adapter accepts (docs/ethernet-ip.md)."""

    max_sessions: int = 16
    max_connections: int = 8  # class 1 + class 3 connections open at once
    min_rpi_us: int = 2000
    max_rpi_us: int = 10_000_000


@dataclass(frozen=True)
class Refusal:
    """Why a Forward Open is refused: its extended status, the words after it, and a text
    naming what was asked (the log line)."""

    status: ExtendedStatus
    text: str
    more: tuple[int, ...] = ()


def refusal(fo: ForwardOpen, identity: Identity, assemblies: Assemblies, limits: Limits, *,
            open_connections: int, duplicate: bool, owned: bool) -> Refusal | None:
    """None when ``fo`` may open; else why not. ``owned``: a class 1 exclusive owner holds
    the output assembly; ``duplicate``: a connection with ``fo``'s triple is open."""
    E = ExtendedStatus  # noqa: N806 - the table's short name
    if duplicate:
        return Refusal(E.DUPLICATE_FORWARD_OPEN, "a connection with this serial is open already")
    trigger = (fo.transport_type_trigger >> 4) & 7
    if fo.transport_class not in (1, 3) or fo.transport_class == 1 and (
            trigger > 1 or fo.transport_type_trigger & 0x80):
        return Refusal(E.TRANSPORT_NOT_SUPPORTED,
                       f"transport 0x{fo.transport_type_trigger:02X} (class 1 cyclic or change "
                       "of state, and class 3, are supported)")
    if open_connections >= limits.max_connections:
        return Refusal(E.OUT_OF_CONNECTIONS, f"{open_connections} connections open, the limit "
                       f"is {limits.max_connections}")
    if fo.path.key is not None:
        found = _key(fo, identity)
        if found is not None:
            return found
    if fo.transport_class == 3:
        if fo.path.class_id != MESSAGE_ROUTER or fo.path.instance != 1:
            return Refusal(E.INVALID_APPLICATION_PATH, "a class 3 connection goes to the "
                           "Message Router (class 2 instance 1)")
        return None
    for name, rpi in (("O→T", fo.o_t_rpi_us), ("T→O", fo.t_o_rpi_us)):
        if not limits.min_rpi_us <= rpi <= limits.max_rpi_us:
            return Refusal(E.RPI_NOT_SUPPORTED, f"{name} RPI {rpi} µs outside "
                           f"{limits.min_rpi_us}..{limits.max_rpi_us} µs")
    a, p = assemblies, fo.path
    if p.class_id != ASSEMBLY or p.points != (a.output_instance, a.input_instance) \
            or p.instance not in (None, a.config_instance):
        return Refusal(E.INVALID_APPLICATION_PATH,
                       f"connection path class {p.class_id} config {p.instance} points "
                       f"{p.points}; this adapter has class 4 config {a.config_instance} points "
                       f"({a.output_instance}, {a.input_instance})")
    if p.data:
        return Refusal(E.INVALID_CONFIGURATION_SIZE, f"{len(p.data)} bytes of configuration "
                       "data; the configuration assembly holds 0", (0,))
    if fo.o_t_parameters.connection_type != 2 or fo.t_o_parameters.connection_type != 2:
        return Refusal(E.INVALID_CONNECTION_TYPE, "only point-to-point class 1 connections are "
                       "supported (no multicast)")
    o_t, t_o = a.output_size + 6, a.input_size + 2
    if fo.o_t_parameters.size != o_t:
        return Refusal(E.INVALID_O_T_SIZE, f"O→T size {fo.o_t_parameters.size}, this adapter "
                       f"consumes {o_t} (sequence count, run/idle header, output assembly)",
                       (o_t,))
    if fo.t_o_parameters.size != t_o:
        return Refusal(E.INVALID_T_O_SIZE, f"T→O size {fo.t_o_parameters.size}, this adapter "
                       f"produces {t_o} (sequence count, input assembly)", (t_o,))
    if owned:
        return Refusal(E.OWNERSHIP_CONFLICT, "an exclusive owner holds the output assembly")
    return None


def _key(fo: ForwardOpen, idt: Identity) -> Refusal | None:
    """The electronic key's check (Vol 1, C-1.4.2): zero fields match anything."""
    assert fo.path.key is not None
    vendor, dtype, product, major, minor = fo.path.key
    if vendor and vendor != idt.vendor_id or product and product != idt.product_code:
        return Refusal(ExtendedStatus.VENDOR_OR_PRODUCT_MISMATCH,
                       f"electronic key vendor {vendor} product {product}")
    if dtype and dtype != idt.device_type:
        return Refusal(ExtendedStatus.DEVICE_TYPE_MISMATCH, f"electronic key device type {dtype}")
    compatible = fo.path.compatibility and minor <= idt.revision[1]
    if major and major != idt.revision[0] or minor and minor != idt.revision[1] \
            and not compatible:
        return Refusal(ExtendedStatus.REVISION_MISMATCH,
                       f"electronic key revision {major}.{minor}")
    return None
