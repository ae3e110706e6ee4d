"""Which peer addresses may open a link: the one check every backend with an allowlist uses.

An allowlist is a list of addresses or networks (``"10.1.2.7"``, ``"10.1.2.0/24"``, IPv6 alike);
empty allows every host. A settings model validates its entries with :func:`networks`, and the
backend asks :meth:`Allowlist.allows` for each connection it accepts.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable

Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def networks(entries: Iterable[str]) -> tuple[Network, ...]:
    """The networks behind ``entries``; ValueError naming the first entry that is not one."""
    out: list[Network] = []
    for entry in entries:
        try:
            out.append(ipaddress.ip_network(entry, strict=False))
        except ValueError:
            raise ValueError(f"allowlist entry {entry!r} is not an address or network") from None
    return tuple(out)


class Allowlist:
    """The peers a link accepts (every host when built from no entries)."""

    def __init__(self, entries: Iterable[str] = ()) -> None:
        self.networks = networks(entries)

    def allows(self, host: str) -> bool:
        """Whether a peer at ``host`` may talk to the link (an IPv4-mapped IPv6 address counts
        as its IPv4 address; a host that is no address is refused when there is a list)."""
        if not self.networks:
            return True
        try:
            addr = ipaddress.ip_address(host)
        except ValueError:
            return False
        if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
            addr = addr.ipv4_mapped
        return any(addr in net for net in self.networks)
