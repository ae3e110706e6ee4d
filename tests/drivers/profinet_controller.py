"""An independent PROFINET IO-controller for the tests: profinet-py (GPL-3.0, a test
dependency only; never imported by product code) driven by JSON lines on stdin, one answer a
line on stdout. Run inside the controller's network namespace (`ip netns exec`).

Commands: {"do": "identify", "name"?} | {"do": "set_name", "mac", "name"} |
{"do": "set_ip", "mac", "ip", "netmask", "gateway", "permanent"} |
{"do": "connect", "name", "slots": [[slot, subslot, in_len, out_len, mod_id, sub_id]...],
 "reduction_ratio", "data_hold_factor"} | {"do": "connect_supervisor", "name"} |
{"do": "prm_end"} | {"do": "app_ready"} |
{"do": "cyclic"} | {"do": "output", "slots": [[slot, subslot, hex]...]} |
{"do": "input", "slot", "subslot"} | {"do": "listen_alarms"} | {"do": "alarms"} |
{"do": "stop_cyclic"} | {"do": "release"} | {"do": "read", "slot", "subslot",
 "index"} | {"do": "write", "slot", "subslot", "index", "hex"} |
{"do": "raw", "hex"} (send a raw frame) | {"do": "udp", "hex", "ip"}.
"""

from __future__ import annotations

import json
import socket
import sys
import traceback

from profinet import dcp, rpc, util
from profinet.cyclic import CyclicController
from profinet.rt import build_iocr_configs

IFACE = sys.argv[1]


def main() -> None:
    sock = util.ethernet_socket(IFACE)
    mac = util.get_mac(IFACE)
    state: dict = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        try:
            answer = run(cmd, sock, mac, state)
            print(json.dumps({"ok": True, **answer}), flush=True)
        except Exception as err:  # noqa: BLE001 - the test reads the error
            print(json.dumps({"ok": False, "error": f"{type(err).__name__}: {err}",
                              "trace": traceback.format_exc()}), flush=True)


def run(cmd: dict, sock, mac: bytes, state: dict) -> dict:
    do = cmd["do"]
    if do == "identify":
        if cmd.get("name"):
            info = rpc.get_station_info(sock, mac, cmd["name"], timeout_sec=2)
            found = [info]
        else:
            xid = dcp.send_discover(sock, mac, response_delay=1)
            found = [dcp.DCPDeviceDescription(m, b) for m, b in
                     dcp.read_response(sock, mac, timeout_sec=2, expected_xid=xid).items()]
        return {"devices": [{"name": d.name, "mac": util.mac2s(d.mac) if isinstance(d.mac, bytes)
                             else d.mac, "ip": d.ip, "vendor_id": d.vendor_id,
                             "device_id": d.device_id,
                             "role": getattr(d, "device_role", None)} for d in found]}
    if do == "set_name":
        return {"set": dcp.set_param(sock, mac, cmd["mac"], "name", cmd["name"], timeout_sec=2)}
    if do == "set_ip":
        return {"set": dcp.set_ip(sock, mac, cmd["mac"], cmd["ip"], cmd["netmask"],
                                  cmd["gateway"], permanent=cmd["permanent"], timeout_sec=2)}
    if do == "connect":
        info = rpc.get_station_info(sock, mac, cmd["name"], timeout_sec=2)
        slots = [rpc.IOSlot(slot=s[0], subslot=s[1], input_length=s[2], output_length=s[3],
                            module_ident=s[4], submodule_ident=s[5]) for s in cmd["slots"]]
        setup = rpc.IOCRSetup(slots=slots, send_clock_factor=32,
                              reduction_ratio=cmd.get("reduction_ratio", 8),
                              watchdog_factor=cmd.get("data_hold_factor", 10),
                              data_hold_factor=cmd.get("data_hold_factor", 10))
        con = rpc.RPCCon(info, timeout=2.0)
        state.update(con=con, info=info, setup=setup)
        result = con.connect(mac, iocr_setup=setup)
        return {"input_frame_id": result.input_frame_id, "output_frame_id":
                result.output_frame_id, "device_mac": util.mac2s(info.mac)
                if isinstance(info.mac, bytes) else info.mac}
    if do == "connect_supervisor":  # a device-access AR (IOSAR), no IOCRs
        info = rpc.get_station_info(sock, mac, cmd["name"], timeout_sec=2)
        rpc.RPCCon(info, timeout=2.0).connect(mac)
        return {}
    con = state.get("con")
    if do == "prm_end":
        con.prm_end()
        return {}
    if do == "app_ready":
        con.application_ready(timeout=5.0)
        return {}
    if do == "cyclic":
        setup = state["setup"]
        in_cr, out_cr = build_iocr_configs(
            setup.slots, con._input_frame_id, con._output_frame_id,
            setup.send_clock_factor, setup.reduction_ratio, setup.watchdog_factor)
        dev_mac = state["info"].mac
        if isinstance(dev_mac, str):
            dev_mac = util.s2mac(dev_mac)
        cyc = CyclicController(IFACE, mac, dev_mac, in_cr, out_cr)
        cyc.start()
        state["cyc"] = cyc
        return {}
    if do == "output":  # [[slot, subslot, hex], ...] in this order
        for slot, subslot, data in cmd["slots"]:
            state["cyc"].set_output_data(slot, subslot, bytes.fromhex(data))
        return {}
    if do == "input":
        data = state["cyc"].get_input_data(cmd["slot"], cmd["subslot"])
        return {"hex": None if data is None else data.hex(), "state":
                state["cyc"].state.value}
    if do == "listen_alarms":
        listener = con.create_alarm_listener(IFACE)
        got = state.setdefault("alarms", [])
        listener.add_callback(lambda a: got.append(
            [a.alarm_type, a.slot_number, a.subslot_number]))
        listener.start()
        state["listener"] = listener
        return {}
    if do == "alarms":
        return {"alarms": state.get("alarms", [])}
    if do == "stop_cyclic":
        cyc = state.pop("cyc")
        cyc.stop()
        return {}
    if do == "release":
        con.disconnect()
        return {}
    if do == "read":
        res = con.read(api=0, slot=cmd["slot"], subslot=cmd["subslot"], idx=cmd["index"])
        return {"hex": bytes(res.payload).hex()}
    if do == "write":
        con.write(api=0, slot=cmd["slot"], subslot=cmd["subslot"], idx=cmd["index"],
                  data=bytes.fromhex(cmd["hex"]))
        return {}
    if do == "raw":
        sock.send(bytes.fromhex(cmd["hex"]))
        return {"mac": util.mac2s(mac)}
    if do == "udp":
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.sendto(bytes.fromhex(cmd["hex"]), (cmd["ip"], 34964))
        s.close()
        return {}
    raise ValueError(f"unknown command {do!r}")


if __name__ == "__main__":
    main()
