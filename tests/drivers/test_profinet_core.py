"""The PROFINET device's sans-I/O core: frames and blocks built here from the spec's byte
layouts (IEC 61158-6-10), the device's answers, the data hold time on a clock we move, and
random bytes that must be counted, never raised. The GSDML shipped is the one generated."""

from __future__ import annotations

import random
import struct
import uuid
import xml.etree.ElementTree as ET

import pytest

from drivers.links import layout
from drivers.links.profinet import blocks, cyclic, gsdml, rpc
from drivers.links.profinet import frames as fr
from drivers.links.profinet import modules as mod
from drivers.links.profinet.device import Device, Identity, valid_station_name

DEV_MAC = bytes.fromhex("020000000001")
PLC_MAC = bytes.fromhex("020000000002")
PLC = ("10.0.0.2", 40000)
AR_UUID = bytes(range(16))
SESSION = 7


def make_device() -> Device:
    return Device(Identity(DEV_MAC, "mvpose-cell-7", (bytes([10, 0, 0, 1]),
                                                      bytes([255, 255, 255, 0]), bytes(4))))


def dcp_frame(service: int, blocks: list[fr.DcpBlock], dst: bytes = fr.DCP_MULTICAST,
              frame_id: int = fr.FRAME_ID_DCP_IDENTIFY_REQ) -> bytes:
    pdu = fr.Dcp(frame_id, service, fr.Service.REQUEST, 0x1234, 1, tuple(blocks))
    return fr.Ethernet(dst, PLC_MAC, fr.ETHERTYPE_PN, pdu.pack()).pack()


def reply_blocks(out_frames: list[bytes]) -> dict[tuple[int, int], bytes]:
    (raw,) = out_frames
    eth = fr.Ethernet.unpack(raw)
    assert eth.dst == PLC_MAC and eth.src == DEV_MAC
    return {b.key: b.data for b in fr.Dcp.unpack(eth.payload).blocks}


def test_identify_all_and_by_name() -> None:
    dev = make_device()
    got = reply_blocks(dev.on_frame(dcp_frame(fr.Service.IDENTIFY,
                                              [fr.DcpBlock(0xFF, 0xFF, b"")]), 0.0).frames)
    assert got[fr.Opt.NAME_OF_STATION][2:] == b"mvpose-cell-7"
    assert got[fr.Opt.DEVICE_ID][2:] == struct.pack(">HH", 0xFFFF, 0x0001)
    assert got[fr.Opt.DEVICE_ROLE][2] == 0x01  # IO-device
    assert got[fr.Opt.IP_PARAMETER][2:6] == bytes([10, 0, 0, 1])
    assert (1, 2) in {tuple(got[fr.Opt.DEVICE_OPTIONS][i:i + 2])
                      for i in range(2, len(got[fr.Opt.DEVICE_OPTIONS]), 2)}
    by_name = dcp_frame(fr.Service.IDENTIFY, [fr.DcpBlock(2, 2, b"mvpose-cell-7")])
    assert len(dev.on_frame(by_name, 0.0).frames) == 1
    other = dcp_frame(fr.Service.IDENTIFY, [fr.DcpBlock(2, 2, b"another-device")])
    assert dev.on_frame(other, 0.0).frames == []


def test_set_name_signal_and_ip() -> None:
    dev = make_device()

    def set_(opt: tuple[int, int], value: bytes, qualifier: bytes = b"\0\0") -> tuple[int, ...]:
        out = dev.on_frame(dcp_frame(fr.Service.SET, [fr.DcpBlock(*opt, qualifier + value)],
                                     DEV_MAC, fr.FRAME_ID_DCP_GET_SET), 0.0)
        return tuple(reply_blocks(out.frames)[fr.Opt.CONTROL_RESPONSE])

    def ip(*suite: str) -> bytes:
        return b"".join(bytes(int(x) for x in a.split(".")) for a in suite)

    assert set_(fr.Opt.NAME_OF_STATION, b"cell-8") == (2, 2, fr.BLOCK_OK)
    assert dev.identity.station_name == "cell-8"
    assert set_(fr.Opt.NAME_OF_STATION, b"Bad_Name") == (2, 2, fr.BLOCK_SET_NOT_POSSIBLE)
    assert set_(fr.Opt.CONTROL_SIGNAL, b"\x01\x00") == (5, 3, fr.BLOCK_OK)
    # a Set IP takes effect (here: the identity; the transport's hook sets the interface)
    assert set_(fr.Opt.IP_PARAMETER, ip("10.0.0.9", "255.255.255.0", "10.0.0.254"),
                b"\0\x01") == (1, 2, fr.BLOCK_OK)
    assert dev.identity.ip == (bytes([10, 0, 0, 9]), bytes([255, 255, 255, 0]),
                               bytes([10, 0, 0, 254]))
    got = reply_blocks(dev.on_frame(dcp_frame(fr.Service.GET, [fr.DcpBlock(1, 2, b"")], DEV_MAC,
                                              fr.FRAME_ID_DCP_GET_SET), 0.0).frames)
    assert got[fr.Opt.IP_PARAMETER][2:] == ip("10.0.0.9", "255.255.255.0", "10.0.0.254")
    # bad suites: SuboptionNotSet, the address unchanged
    for bad in (("10.0.0.7", "255.0.255.0", "0.0.0.0"),  # netmask not contiguous
                ("0.0.0.0", "255.255.255.0", "0.0.0.0"),
                ("224.0.0.9", "255.255.255.0", "0.0.0.0"),  # multicast
                ("10.0.0.0", "255.255.255.0", "0.0.0.0"),  # the network's own address
                ("10.0.0.7", "255.255.255.0", "10.0.1.1")):  # gateway outside the subnet
        assert set_(fr.Opt.IP_PARAMETER, ip(*bad)) == (1, 2, fr.BLOCK_SUBOPTION_NOT_SET), bad
    assert set_(fr.Opt.IP_PARAMETER, ip("10.0.0.7")) == (1, 2, fr.BLOCK_SUBOPTION_NOT_SET)
    assert dev.identity.ip[0] == bytes([10, 0, 0, 9])
    got = reply_blocks(dev.on_frame(dcp_frame(fr.Service.GET, [fr.DcpBlock(2, 2, b"")], DEV_MAC,
                                              fr.FRAME_ID_DCP_GET_SET), 0.0).frames)
    assert got[fr.Opt.NAME_OF_STATION][2:] == b"cell-8"


def test_set_ip_refused_by_the_setting_said_once_and_a_failing_host() -> None:
    dev = Device(Identity(DEV_MAC, "cell-8"), accept_ip=False)
    req = dcp_frame(fr.Service.SET, [fr.DcpBlock(1, 2, b"\0\x01" + bytes([10, 0, 0, 9]) +
                                                 bytes([255, 255, 255, 0]) + bytes(4))],
                    DEV_MAC, fr.FRAME_ID_DCP_GET_SET)
    outs = [dev.on_frame(req, 0.0) for _ in range(3)]
    assert {tuple(reply_blocks(o.frames)[fr.Opt.CONTROL_RESPONSE]) for o in outs} == {
        (1, 2, fr.BLOCK_SET_NOT_POSSIBLE)}
    assert [e.kind for o in outs for e in o.events] == ["ip_refused"]
    assert "accept_ip_from_controller is false" in outs[0].events[0].text
    dev = Device(Identity(DEV_MAC, "cell-8"), set_ip=lambda suite, permanent: "no such device")
    out = dev.on_frame(req, 0.0)
    assert reply_blocks(out.frames)[fr.Opt.CONTROL_RESPONSE][2] == fr.BLOCK_RESOURCE_ERROR
    assert dev.identity.ip[0] == bytes(4) and "no such device" in out.events[0].text


def iocr(itype: int, ref: int, rr: int, data: list[tuple[int, int, int]],
         iocs: list[tuple[int, int, int]], length: int, hold: int = 3) -> bytes:
    body = struct.pack(">HHHIHHHHHHIHHH", itype, ref, 0x8892, 1, length,
                       0xC001 if itype == 1 else 0xFFFF, 32, rr, 1, 0, 0xFFFFFFFF, hold, hold,
                       0xC000) + bytes(6) + struct.pack(">H", 1) + struct.pack(">I", 0)
    body += struct.pack(">H", len(data)) + b"".join(struct.pack(">HHH", *d) for d in data)
    body += struct.pack(">H", len(iocs)) + b"".join(struct.pack(">HHH", *d) for d in iocs)
    return blocks.block(blocks.BLOCK_IOCR_REQ, body)


def connect_body(subs: list[mod.Submodule], rr: int = 4) -> bytes:
    name = b"plc"
    ar = blocks.block(blocks.BLOCK_AR_REQ, struct.pack(">H", 1) + AR_UUID
                      + struct.pack(">H", SESSION) + PLC_MAC + uuid.uuid4().bytes
                      + struct.pack(">IHHH", 0x11, 100, 0x8892, len(name)) + name)
    # input CR: the result's data and IOPS, then IOCS for the output submodules
    ins = [s for s in subs if s.input_length or not s.output_length]
    outs = [s for s in subs if s.output_length]
    at, in_data, in_iocs = 0, [], []
    for s in ins:
        in_data.append((s.slot, s.subslot, at))
        at += s.input_length + 1
    for s in outs:
        in_iocs.append((s.slot, s.subslot, at))
        at += 1
    in_len = max(40, at)
    at, out_data, out_iocs = 0, [], []
    for s in outs:
        out_data.append((s.slot, s.subslot, at))
        at += s.output_length + 1
    for s in ins:
        out_iocs.append((s.slot, s.subslot, at))
        at += 1
    alarm = blocks.block(blocks.BLOCK_ALARM_CR_REQ,
                         struct.pack(">HHIHHHHHH", 1, 0x8892, 0, 1, 3, 1, 200, 0xC000, 0xA000))
    exp = struct.pack(">H", len(subs))
    for s in subs:
        kind = (1 if s.input_length else 0) | (2 if s.output_length else 0)
        exp += struct.pack(">IHIHH", 0, s.slot, s.module_ident, 0, 1)
        exp += struct.pack(">HIH", s.subslot, s.submodule_ident, kind)
        if kind in (0, 1, 3):
            exp += struct.pack(">HHBB", 1, s.input_length, 1, 1)
        if kind in (2, 3):
            exp += struct.pack(">HHBB", 2, s.output_length, 1, 1)
    return (ar + iocr(1, 1, rr, in_data, in_iocs, in_len)
            + iocr(2, 2, rr, out_data, out_iocs, max(40, at)) + alarm
            + blocks.block(blocks.BLOCK_EXPECTED_SUBMODULE, exp))


def call(dev: Device, opnum: int, body: bytes, now: float = 0.0) -> tuple[int, list[tuple[int,
                                                                                          bytes]]]:
    ndr = rpc.Ndr(4096, body, 4096).pack(False, response=False)
    head = rpc.RpcHeader(rpc.REQUEST, rpc.object_uuid(1, 1, 0xFFFF), rpc.IFACE_DEVICE,
                         uuid.uuid4(), 0, opnum, len(ndr), little=False)
    out = dev.on_datagram(head.pack() + ndr, PLC, now)
    ((data, addr),) = out.datagrams
    assert addr == PLC
    reply = rpc.RpcHeader.unpack(data)
    assert reply.ptype == rpc.RESPONSE and reply.opnum == opnum
    answer = rpc.Ndr.unpack(data[rpc.HEADER_SIZE:], reply.little)
    return answer.first, blocks.split_blocks(answer.body) if answer.body else []


def control(command: int, btype: int) -> bytes:
    return blocks.Control(btype, AR_UUID, SESSION, command).pack()


def test_connect_prm_end_application_ready_and_cyclic_data() -> None:
    dev = make_device()
    status, got = call(dev, rpc.OP_CONNECT, connect_body(list(mod.SUBMODULES)))
    assert status == 0
    kinds = [b[0] for b in got]
    assert kinds == [0x8101, 0x8102, 0x8102, 0x8103]  # no ModuleDiffBlock: all fit
    out_fid = struct.unpack(">HHH", got[2][1])[2]
    assert fr.FRAME_ID_RTC1_MIN <= out_fid <= fr.FRAME_ID_RTC1_MAX
    status, got = call(dev, rpc.OP_CONTROL, control(blocks.CMD_PRM_END, blocks.BLOCK_PRM_END))
    assert status == 0 and got[0][0] == 0x8110
    tick = dev.tick(0.001)
    ((app_ready, addr),) = tick.datagrams
    assert addr == (PLC[0], rpc.RPC_PORT)
    head = rpc.RpcHeader.unpack(app_ready)
    assert head.interface == rpc.IFACE_CONTROLLER and head.opnum == rpc.OP_CONTROL
    ndr = rpc.Ndr.unpack(app_ready[rpc.HEADER_SIZE:], head.little)
    assert blocks.Control.unpack(*blocks.split_blocks(ndr.body)[0]).command == blocks.CMD_APP_READY
    confirm = rpc.Ndr(0, control(blocks.CMD_DONE, 0x8112), 0).pack(True, response=True)
    done = rpc.RpcHeader(rpc.RESPONSE, head.object, head.interface, head.activity, head.seqnum,
                         head.opnum, len(confirm))
    assert [e.kind for e in dev.on_datagram(done.pack() + confirm, addr, 0.002).events] == [
        "running"]
    # the input frame carries the input image at the result's offset, big-endian
    dev.input_image = bytes(range(layout.INPUT_SIZE))
    assert dev.ar is not None
    frame = fr.Ethernet.unpack(cyclic.input_frame(dev.ar, dev.input_image, dev.identity.mac))
    assert frame.dst == PLC_MAC and frame.vlan_tci == 0xC000
    rt = fr.RtFrame.unpack(frame.payload, dev.ar.input_cr.data_length)
    obj = next(o for o in dev.ar.input_cr.data if o.slot == mod.RESULT.slot)
    assert rt.c_sdu[obj.offset:obj.offset + layout.INPUT_SIZE] == dev.input_image
    assert rt.c_sdu[obj.offset + layout.INPUT_SIZE] == fr.IOXS_GOOD
    assert rt.data_status == fr.DATA_STATUS_GOOD
    # an output frame from the controller becomes the output image
    sdu = bytearray(dev.ar.output_cr.data_length)
    for o in dev.ar.output_cr.data:
        sub = mod.find(o.slot, o.subslot)
        assert sub is not None
        lo, n = sub.output
        sdu[o.offset:o.offset + n] = bytes((lo + i) & 0xFF for i in range(n))
        sdu[o.offset + n] = fr.IOXS_GOOD
    out_frame = fr.Ethernet(DEV_MAC, PLC_MAC, fr.ETHERTYPE_PN, fr.RtFrame(
        out_fid, bytes(sdu), 128, fr.DATA_STATUS_GOOD).pack()).pack()
    got = dev.on_frame(out_frame, 0.003)
    assert got.output == bytes(i & 0xFF for i in range(layout.OUTPUT_SIZE))
    # the data hold time (3 × 4 ms) ends the AR; the outputs stay (their heartbeat stops)
    assert dev.tick(0.010).events == []
    assert [e.kind for e in dev.tick(0.020).events] == ["data_hold_expired"]
    assert dev.ar is None and dev.output_image == got.output


def test_wrong_submodules_get_a_module_diff_block() -> None:
    dev = make_device()
    wrong = [mod.Submodule("x", 1, 1, 0x10, 0x99, output=mod.HANDSHAKE.output),
             mod.Submodule("missing", 9, 1, 0x77, 0x78, input=(0, 4)), mod.RESULT]
    status, got = call(dev, rpc.OP_CONNECT, connect_body(wrong))
    assert status == 0 and got[-1][0] == 0x8104
    body = got[-1][1]
    n_apis, api, n_mods = struct.unpack_from(">HIH", body, 0)
    assert (n_apis, api, n_mods) == (1, 0, 2)
    slot, mident, mstate, n_sub, subslot, sident, sstate = struct.unpack_from(">HIHHHIH", body, 8)
    assert (slot, mident, mstate, sident, sstate) == (1, 0x10, blocks.MODULE_PROPER, 0x11,
                                                      blocks.SUBMODULE_WRONG)
    assert dev.stats.module_diffs == 1


def test_refused_connects_and_release() -> None:
    dev = make_device()
    status, _ = call(dev, rpc.OP_CONNECT, connect_body(list(mod.SUBMODULES), rr=16).replace(
        struct.pack(">HH", 32, 16), struct.pack(">HH", 1, 1)))  # 31.25 µs: below 1 ms
    assert status >> 24 == 0xDB and dev.ar is None
    assert call(dev, rpc.OP_CONNECT, connect_body(list(mod.SUBMODULES)))[0] == 0
    status, got = call(dev, rpc.OP_RELEASE, control(blocks.CMD_RELEASE, blocks.BLOCK_RELEASE))
    assert status == 0 and got[0][0] == 0x8114 and dev.ar is None
    status, _ = call(dev, rpc.OP_RELEASE, control(blocks.CMD_RELEASE, blocks.BLOCK_RELEASE))
    assert status >> 24 == 0xDE  # no such AR any more


def test_read_im0_and_real_identification() -> None:
    dev = make_device()
    req = blocks.block(blocks.BLOCK_READ_REQ, struct.pack(">H", 1) + bytes(16)
                    + struct.pack(">IHHHHI", 0, 0, 1, 0, 0xAFF0, 4096) + bytes(24))
    status, got = call(dev, rpc.OP_READ, req)
    assert status == 0 and got[0][0] == 0x8009 and got[1][0] == blocks.BLOCK_IM0
    assert struct.unpack_from(">H", got[1][1], 0)[0] == 0xFFFF
    assert got[1][1][2:22].strip() == b"MVPOSE-PN"
    req = req.replace(struct.pack(">HI", 0xAFF0, 4096), struct.pack(">HI", 0xF000, 4096))
    status, got = call(dev, rpc.OP_READ, req)
    (n_slots,) = struct.unpack_from(">H", got[1][1], 0)
    assert n_slots == len({s.slot for s in mod.SUBMODULES})


def test_random_bytes_are_counted_never_raised() -> None:
    dev = make_device()
    rnd = random.Random(25)
    valid = [dcp_frame(fr.Service.IDENTIFY, [fr.DcpBlock(0xFF, 0xFF, b"")])]
    body = connect_body(list(mod.SUBMODULES))
    ndr = rpc.Ndr(4096, body, 4096).pack(False, response=False)
    dgram = rpc.RpcHeader(rpc.REQUEST, uuid.uuid4(), rpc.IFACE_DEVICE, uuid.uuid4(), 0,
                          rpc.OP_CONNECT, len(ndr), little=False).pack() + ndr
    for i in range(3000):
        raw = bytearray(valid[0] if i % 2 else dgram)
        for _ in range(rnd.randint(1, 8)):
            raw[rnd.randrange(len(raw))] = rnd.randrange(256)
        cut = bytes(raw[:rnd.randint(0, len(raw))]) if i % 3 == 0 else bytes(raw)
        dev.on_frame(cut, i * 0.001)
        dev.on_datagram(cut, PLC, i * 0.001)
        dev.tick(i * 0.001)
    for opnum in range(8):  # every operation with a body cut anywhere
        for n in range(0, 120, 7):
            ndr = rpc.Ndr(4096, body[:n], 4096).pack(True, response=False)
            head = rpc.RpcHeader(rpc.REQUEST, uuid.uuid4(), rpc.IFACE_DEVICE, uuid.uuid4(), 0,
                                 opnum, len(ndr))
            dev.on_datagram(head.pack() + ndr, PLC, 5.0)
    assert dev.stats.malformed > 100


@pytest.mark.parametrize(("name", "ok"), [("mvpose-cell-7", True), ("a.b-c", True),
                                          ("Cell", False), ("-x", False), ("port-001", False),
                                          ("", False), ("x" * 64, False)])
def test_station_names(name: str, ok: bool) -> None:
    assert valid_station_name(name) is ok


def test_the_shipped_gsdml_is_the_generated_one() -> None:
    assert gsdml.SHIPPED.read_text(encoding="utf-8") == gsdml.render(), (
        "regenerate it: python -m drivers.links.profinet.gsdml")
    ns = {"g": "http://www.profibus.com/GSDML/2003/11/DeviceProfile"}
    root = ET.fromstring(gsdml.render().encode())
    idents = {int(m.get("ModuleIdentNumber", "0"), 16)
              for m in root.iterfind(".//g:ModuleItem", ns)}
    assert idents == {s.module_ident for s in mod.SUBMODULES if s.slot > 0}
    outputs = root.iterfind(".//g:ModuleItem[@ID='IDM_1']//g:Output/g:DataItem", ns)
    assert len(list(outputs)) == len(mod.output_fields(mod.HANDSHAKE))
    dap = root.find(".//g:DeviceAccessPointItem//g:VirtualSubmoduleItem[@ID='IDS_DAP']", ns)
    assert dap is not None and dap.get("Writeable_IM_Records") == "1 2 3 4"


def test_diagnosis_alarms_one_in_flight_acked_and_retried() -> None:
    from drivers.links.profinet import alarms as al

    cr = al.AlarmCr(PLC_MAC, DEV_MAC, controller_ref=3, device_ref=1, high=False,
                    timeout_s=0.1, retries=3)
    (first,) = cr.diagnosis(True, al.ERROR_CAMERA_DOWN, 0.0)
    assert cr.diagnosis(False, al.ERROR_CAMERA_DOWN, 0.0) == []  # window of one: queued
    eth = fr.Ethernet.unpack(first)
    assert struct.unpack_from(">H", eth.payload)[0] == fr.FRAME_ID_ALARM_LOW
    rta = al.Rta.unpack(eth.payload[2:])
    assert (rta.dst_ref, rta.src_ref, rta.pdu_type, rta.send_seq) == (3, 1, al.PDU_DATA, 0xFFFF)
    ((btype, body),) = blocks.split_blocks(rta.var)
    alarm_type, _api, slot, subslot = struct.unpack_from(">HIHH", body, 0)
    assert (btype, alarm_type, slot, subslot) == (0x0002, al.ALARM_DIAGNOSIS, 3, 1)
    assert struct.unpack_from(">HHHH", body, 20) == (al.USI_CHANNEL_DIAGNOSIS,
                                                     al.WHOLE_SUBMODULE, 1 << 11,
                                                     al.ERROR_CAMERA_DOWN)
    assert cr.tick(0.05) == [] and cr.tick(0.11) == [first]  # retried after the RTA timeout
    ack = al.Rta(1, 3, al.PDU_ACK, 1, 0xFFFF, 0xFFFF)
    (second,) = cr.on_rta(ack, 0.12)  # acked: the disappearing one goes out
    rta2 = al.Rta.unpack(fr.Ethernet.unpack(second).payload[2:])
    assert rta2.send_seq == 0
    assert struct.unpack_from(">H", blocks.split_blocks(rta2.var)[0][1], 0)[0] == \
        al.ALARM_DIAGNOSIS_DISAPPEARS
    assert cr.acked == 1
    assert cr.on_rta(al.Rta(9, 3, al.PDU_ACK, 1, 0, 0), 0.13) == []  # not our endpoint


def test_lldp_names_the_station_and_port() -> None:
    eth = fr.Ethernet.unpack(fr.lldp_frame(DEV_MAC, "mvpose-cell-7", "port-001"))
    assert (eth.dst, eth.src, eth.ethertype) == (fr.LLDP_MULTICAST, DEV_MAC, fr.ETHERTYPE_LLDP)
    tlvs, at = {}, 0
    while at < len(eth.payload):
        head, = struct.unpack_from(">H", eth.payload, at)
        kind, n = head >> 9, head & 0x1FF
        tlvs[kind] = eth.payload[at + 2:at + 2 + n]
        at += 2 + n
        if kind == 0:
            break
    assert tlvs[1] == b"\x07mvpose-cell-7"  # chassis id: NameOfStation, locally assigned
    assert tlvs[2] == b"\x07port-001"
    assert struct.unpack(">H", tlvs[3]) == (20,)


def test_the_station_files_block_is_checked_field_by_field() -> None:
    from drivers.links import LinkSettingsError, link_settings
    from drivers.links.profinet.settings import ProfinetLinkConfig

    assert "profinet" not in link_settings({})  # no PROFINET unless the station file names it
    cfg = link_settings({"profinet": {"interface": "eth1", "station_name": "cell-7"}})["profinet"]
    assert isinstance(cfg, ProfinetLinkConfig) and cfg.min_cycle_ms == 1.0
    with pytest.raises(LinkSettingsError) as err:
        link_settings({"profinet": {"station_name": "Cell_7", "cycle": 4, "min_cycle_ms": 0.5}})
    where = sorted(p[0] for p in err.value.problems)
    assert where == ["links.profinet.cycle", "links.profinet.min_cycle_ms",
                     "links.profinet.station_name"]
