"""The EtherNet/IP adapter backend of the link seam (docs/ethernet-ip.md):
``codec`` and ``cip`` (frames); the sans-I/O core: ``session`` (encapsulation), ``adapter``
(Connection Manager and class 1 I/O), ``admission`` (a Forward Open's checks), ``objects``
(the CIP objects); ``transport`` (asyncio sockets), ``link`` (the Link), ``settings``,
``eds`` (the EDS from the layout) and ``twin`` (the PLC twin's class 1 port)."""

from .link import EnipLink

__all__ = ["EnipLink"]
