"""What the PROFINET device keeps across its restarts and how a DCP Set IP reaches the host:
the state file ``<state_dir>/device.json`` (the permanent IP suite, the interface's address
before the controller first set one, the I&M1..4 records), and the interface's IPv4 address
set with iproute2's ``ip`` (the device's process is root or CAP_NET_ADMIN already).
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import subprocess
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

Suite = tuple[bytes, bytes, bytes]  # address, netmask, gateway


def dotted(raw: bytes) -> str:
    return str(ipaddress.IPv4Address(raw))


def suite_from(values: list[str]) -> Suite:
    a, m, g = (ipaddress.IPv4Address(v).packed for v in values)
    return a, m, g


class DeviceStore:
    """The device's state file, written whole and atomically (a crash leaves the old one)."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.path = Path(state_dir) / "device.json"

    def load(self) -> dict[str, Any]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as err:
            log.warning("PROFINET state file %s unreadable (%s): starting without it",
                        self.path, err)
            return {}
        return data if isinstance(data, dict) else {}

    def save(self, data: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True), encoding="utf-8")
        os.replace(tmp, self.path)


class HostIpError(OSError):
    """The interface's address could not be set (names the command and its error)."""


def _ip(*args: str) -> None:
    try:
        done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise HostIpError(f"`ip {' '.join(args)}` failed: {err}") from None
    if done.returncode:
        raise HostIpError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def apply(iface: str, suite: Suite) -> None:
    """Give ``iface`` the address/netmask of ``suite`` as its only IPv4 address, and a
    default route over the gateway (metric 1000, so that the host's own default route, if
    any, stays first) unless the gateway is 0.0.0.0 or the address itself."""
    addr, mask, gw = suite
    prefix = ipaddress.IPv4Network(f"0.0.0.0/{dotted(mask)}").prefixlen
    _ip("-4", "addr", "flush", "dev", iface)
    if any(addr):
        _ip("addr", "add", f"{dotted(addr)}/{prefix}", "dev", iface)
    if any(gw) and gw != addr:
        _ip("route", "replace", "default", "via", dotted(gw), "dev", iface, "metric", "1000")
