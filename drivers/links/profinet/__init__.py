"""PROFINET IO-device backend (conformance class A, RT_CLASS_1): DCP, DCE/RPC, cyclic RT data,
LLDP; the device runs in a process of its own (:mod:`.transport`), the handshake on the
station's loop (:mod:`.link`). docs/profinet.md."""

from .link import ProfinetLink

__all__ = ["ProfinetLink"]
