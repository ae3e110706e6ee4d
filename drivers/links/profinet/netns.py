"""A line of one cable for the demo and the benches: a veth pair whose device end stays in this
network namespace and whose controller end is in a namespace of its own, so that the PLC twin
and the station exchange real Ethernet frames and UDP datagrams (a PROFINET device and its
controller in one namespace would reach each other over loopback, not the wire).

Names and addresses are new for every line (random, in 10.250.0.0/16, /30 each), so two demos
and the tests never collide; :meth:`VethLine.remove` takes both away (also after a failure).
Creating one needs root (CAP_NET_ADMIN).
"""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
from dataclasses import dataclass


class NetnsError(RuntimeError):
    """The line could not be made (names the command and its error)."""


def why_not() -> str | None:
    """Why this process cannot make a line, or None."""
    if os.geteuid() != 0:
        return ("it creates a network namespace and a veth pair, which needs root: run it as "
                "root (e.g. sudo)")
    if shutil.which("ip") is None:
        return "it needs the `ip` command (iproute2) to create a network namespace"
    return None


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode:
        raise NetnsError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


@dataclass(frozen=True)
class VethLine:
    """The device's interface here, the controller's in ``ns``, with their addresses."""

    ns: str
    device_if: str
    controller_if: str
    device_ip: str
    controller_ip: str

    @classmethod
    def create(cls) -> VethLine:
        tag = secrets.token_hex(3)
        k = secrets.randbelow(1 << 14)  # a /30 of 10.250.0.0/16
        base = f"10.250.{k >> 6}.{(k & 63) * 4}"
        net = base.rsplit(".", 1)[0]
        last = int(base.rsplit(".", 1)[1])
        line = cls(f"mvpn{tag}", f"mvpd{tag}", f"mvpc{tag}", f"{net}.{last + 1}",
                   f"{net}.{last + 2}")
        _ip("netns", "add", line.ns)
        try:
            _ip("link", "add", line.device_if, "type", "veth", "peer", "name",
                line.controller_if)
            _ip("link", "set", line.controller_if, "netns", line.ns)
            _ip("addr", "add", f"{line.device_ip}/30", "dev", line.device_if)
            _ip("link", "set", line.device_if, "up")
            _ip("-n", line.ns, "addr", "add", f"{line.controller_ip}/30", "dev",
                line.controller_if)
            _ip("-n", line.ns, "link", "set", line.controller_if, "up")
            _ip("-n", line.ns, "link", "set", "lo", "up")
        except BaseException:
            line.remove()
            raise
        return line

    def remove(self) -> None:
        """Both ends and the namespace (deleting one end of a veth pair deletes both)."""
        subprocess.run(["ip", "link", "del", self.device_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", self.ns], capture_output=True)
