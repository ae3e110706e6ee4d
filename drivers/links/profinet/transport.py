"""The PROFINET device's sockets, in a process of its own (``python -m
drivers.links.profinet.transport``): a raw AF_PACKET socket on the configured interface
(DCP, RT, LLDP), the RPC socket on UDP 34964, and the station over a SEQPACKET socketpair whose
descriptor is the second argument. A frame cycle never waits for the station's GIL.

Messages on the pair, one per packet: to the child ``I`` + the INPUT block (big-endian),
``A`` + a JSON diagnosis (``{"source", "appears", "error_type"}``) and ``Q`` (stop); to the
station ``O`` + the OUTPUT block when the controller's outputs changed,
``E`` + a JSON event (``{"kind", "text"}``; kind ``started`` with the MAC, ``error`` with a
start-up problem, then the device's events) and ``S`` + JSON stats every second.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import socket
import struct
import time
from collections import deque
from typing import Any

from . import child, hostip
from . import frames as fr
from .device import Device, Identity, Out

ETH_P_ALL = 0x0003
SIOCGIFADDR = 0x8915
SIOCGIFNETMASK = 0x891B
LLDP_EVERY_S = 5.0
STATS_EVERY_S = 1.0


def _ifaddr(sock: socket.socket, iface: str, request: int) -> bytes:
    try:
        raw = fcntl.ioctl(sock.fileno(), request, struct.pack("256s", iface.encode()[:15]))
        return raw[20:24]
    except OSError:
        return bytes(4)


def open_sockets(iface: str, rpc_host: str, rpc_port: int, who: str = "the PROFINET link"
                 ) -> tuple[socket.socket, socket.socket, bytes, tuple[bytes, bytes, bytes]]:
    """The raw socket on ``iface``, the RPC socket, the interface's MAC and IP parameters
    (``who`` opens them, for the error that says why not)."""
    try:
        raw = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    except PermissionError:
        raise PermissionError(
            f"{who} needs raw Ethernet sockets: run it as root or give its python CAP_NET_RAW "
            "(setcap cap_net_raw+ep)") from None
    try:
        raw.bind((iface, 0))
    except OSError as err:
        raw.close()
        raise OSError(f"PROFINET interface {iface!r}: {err.strerror}") from None
    mac = raw.getsockname()[4][:6]
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    udp.bind((rpc_host, rpc_port))
    ip = (_ifaddr(udp, iface, SIOCGIFADDR), _ifaddr(udp, iface, SIOCGIFNETMASK), bytes(4))
    return raw, udp, mac, ip


def _udp(host: str, port: int) -> socket.socket:
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        udp.bind((host, port))
    except OSError:
        udp.close()
        raise
    return udp


def _restore_ip(iface: str, state: dict[str, Any], store: hostip.DeviceStore
                ) -> tuple[hostip.Suite | None, str]:
    """At the device's start: the permanent IP suite a controller set (applied again if the
    interface lost it), or, after a temporary one, the interface's own address back. The
    suite in effect (None: the interface's own) and a note for the start-up line. What was
    set on another interface (the station file changed) is forgotten."""
    if state.get("interface", iface) != iface:
        for key in ("interface", "ip", "host_ip"):
            state.pop(key, None)
        store.save(state)
    if "ip" in state:
        suite = hostip.suite_from(state["ip"])
        probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        with probe:
            current = (_ifaddr(probe, iface, SIOCGIFADDR), _ifaddr(probe, iface,
                                                                   SIOCGIFNETMASK))
        if current != (suite[0], suite[1]):
            hostip.apply(iface, suite)
        return suite, f", IP {state['ip'][0]} (set permanently by DCP)"
    if "host_ip" in state:
        addr, mask = state.pop("host_ip")
        hostip.apply(iface, hostip.suite_from([addr, mask, "0.0.0.0"]))
        store.save(state)
        return None, f", the temporary DCP address dropped: {addr} again"
    return None, ""


def _stored_im(state: dict[str, Any]) -> dict[int, bytes]:
    try:
        return {int(k, 16): bytes.fromhex(v) for k, v in state.get("im", {}).items()}
    except (AttributeError, TypeError, ValueError):
        return {}


def realtime(priority: int) -> str:
    """Put this process under SCHED_FIFO at ``priority`` (0: leave it), so that a loaded host's
    other work does not delay a cycle; what it got, said for the log and the status."""
    if priority <= 0:
        return "normal scheduling"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as err:  # no CAP_SYS_NICE, or a container without real-time budget
        return f"normal scheduling (SCHED_FIFO {priority} refused: {err.strerror})"
    return f"SCHED_FIFO {priority}"


def serve(cfg: dict[str, Any], pair: socket.socket) -> None:
    def event(kind: str, text: str, **more: Any) -> None:
        pair.send(b"E" + json.dumps({"kind": kind, "text": text, **more}).encode())

    iface, port = cfg["interface"], cfg["rpc_port"]
    store = hostip.DeviceStore(cfg["state_dir"])
    state = store.load()
    try:
        kept, ip_note = _restore_ip(iface, state, store)
        host = cfg["rpc_host"] if kept is None else hostip.dotted(kept[0])
        raw, udp, mac, ip = open_sockets(iface, host, port)
    except OSError as err:
        event("error", str(err))
        return
    if kept is not None:
        ip = kept

    def set_ip(suite: hostip.Suite, permanent: bool) -> str | None:
        """DCP Set IP taking effect: the interface's address, the RPC socket, the state."""
        nonlocal udp
        current = (_ifaddr(udp, iface, SIOCGIFADDR), _ifaddr(udp, iface, SIOCGIFNETMASK))
        try:
            if (suite[0], suite[1]) != current or suite[2] != dev.identity.ip[2]:
                state["interface"] = iface
                state.setdefault("host_ip", [hostip.dotted(x) for x in current])
                hostip.apply(iface, suite)
            if suite[0] != current[0] or udp.getsockname()[0] != hostip.dotted(suite[0]):
                udp.close()
                udp = _udp(hostip.dotted(suite[0]), port)
            if permanent:
                state["ip"] = [hostip.dotted(x) for x in suite]
            else:  # a temporary address is dropped on restart, and so is the stored one
                state.pop("ip", None)
            store.save(state)
        except OSError as err:
            if udp.fileno() < 0:
                udp = _udp(hostip.dotted(current[0]), port)
            return str(err)
        return None

    dev = Device(Identity(mac, cfg["station_name"], ip, cfg["vendor_id"], cfg["device_id"],
                          order_id=cfg["order_id"], serial=cfg["serial"]),
                 min_cycle_ms=cfg["min_cycle_ms"], input_phase_ms=cfg.get("input_phase_ms"),
                 accept_ip=cfg.get("accept_ip_from_controller", True), set_ip=set_ip,
                 im=_stored_im(state))
    scheduling = realtime(cfg.get("realtime_priority", 0))
    event("started", f"PROFINET device {cfg['station_name']!r} on {iface} "
          f"({fr.mac_text(mac)}), {scheduling}{ip_note}", mac=fr.mac_text(mac))
    next_lldp = next_stats = time.monotonic()
    intervals: deque[float] = deque(maxlen=2000)  # between input frames sent, for the jitter
    last_cyclic = [0.0]

    def send(sock: socket.socket, data: bytes, addr: tuple[str, int] | None = None) -> None:
        # a link that is down or a controller that went away (ICMP unreachable) is counted,
        # never the end of the device
        try:
            sock.send(data) if addr is None else sock.sendto(data, addr)
        except OSError as err:
            dev.stats.send_errors += 1
            dev.stats.last_errors = [*dev.stats.last_errors[-9:], f"send failed: {err}"]

    def emit(out: Out) -> None:
        for frame in out.frames:
            send(raw, frame)
        if out.cyclic:
            t = time.monotonic()
            if last_cyclic[0]:
                intervals.append(t - last_cyclic[0])
            last_cyclic[0] = t
        for data, addr in out.datagrams:
            send(udp, data, addr)
        for ev in out.events:
            event(ev.kind, ev.text)
        if out.output is not None:
            pair.send(b"O" + out.output)
        if out.im_changed:
            state["im"] = {f"0x{k:04X}": v.hex() for k, v in dev.im.items()}
            try:
                store.save(state)
            except OSError as err:
                event("error", f"I&M records not stored in {store.path}: {err}")

    while True:
        now = time.monotonic()
        timeout = max(0.0, dev.next_deadline(now) - now)
        ready, _, _ = select.select([raw, udp, pair], [], [], timeout)
        now = time.monotonic()
        if pair in ready:
            msg = pair.recv(4096)
            if not msg or msg[:1] == b"Q":
                break
            if msg[:1] == b"I" and len(msg) - 1 == len(dev.input_image):
                dev.input_image = msg[1:]
            elif msg[:1] == b"A":
                diag = json.loads(msg[1:])
                emit(dev.diagnosis(diag["source"], diag["appears"], diag["error_type"], now))
        if raw in ready:
            for _ in range(64):
                try:
                    frame = raw.recv(2048, socket.MSG_DONTWAIT)
                except OSError:  # nothing more, or the interface went down
                    break
                emit(dev.on_frame(frame, now))
        if udp in ready:
            try:
                data, addr = udp.recvfrom(8192)
            except OSError:  # an ICMP error of an earlier datagram (the controller went away)
                pass
            else:
                emit(dev.on_datagram(data, addr, now))
        emit(dev.tick(time.monotonic()))
        if now >= next_lldp:
            send(raw, fr.lldp_frame(mac, dev.identity.station_name, "port-001"))
            next_lldp = now + LLDP_EVERY_S
        if now >= next_stats:
            st = dev.stats
            pair.send(b"S" + json.dumps({
                **{k: v for k, v in vars(st).items() if k != "last_errors"},
                "last_errors": st.last_errors[-5:], "station_name": dev.identity.station_name,
                "dcp_requests": dev.dcp.requests, "scheduling": scheduling,
                **_jitter(intervals),
                "ar": None if dev.ar is None else {
                    "controller": dev.ar.controller_addr[0], "phase": dev.ar.phase,
                    "cycle_ms": dev.ar.input_cr.cycle_us / 1000,
                    "data_hold_ms": dev.ar.hold_s * 1000, "alarms_sent": dev.ar.alarm.sent,
                    "phase_moves": dev.ar.realigned,
                    "alarms_acked": dev.ar.alarm.acked},
                "diagnoses": sorted(dev.diagnoses)}).encode())
            next_stats = now + STATS_EVERY_S


def _jitter(intervals: deque[float]) -> dict[str, float]:
    """The input frames' interval p50 and p99 − p50 (the cycle jitter), in ms."""
    if len(intervals) < 10:
        return {}
    ordered = sorted(intervals)
    p50 = ordered[len(ordered) // 2]
    p99 = ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))]
    return {"cycle_p50_ms": round(p50 * 1000, 3), "cycle_jitter_ms": round((p99 - p50) * 1000, 3)}


if __name__ == "__main__":
    child.main(serve)
