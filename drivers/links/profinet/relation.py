"""The IO AR's life over RPC (IEC 61158-6-10): Connect (its checks, the module diff and the
AR it opens), Control (PrmBegin, PrmEnd), Release, and the device's ApplicationReady request
with the controller's confirmation that starts the data exchange. Functions over the
:class:`~.device.Device`'s state; each RPC operation answers (PNIO status, body).
"""

from __future__ import annotations

import uuid
from typing import TYPE_CHECKING

from .. import layout
from . import blocks, rpc
from . import frames as fr
from . import modules as mod
from .alarms import AlarmCr
from .dcp import Event
from .state import Ar, Out

if TYPE_CHECKING:
    from .device import Device


def connect(dev: Device, body: bytes, addr: tuple[str, int], now: float,
            out: Out) -> tuple[int, bytes]:
    parts = blocks.split_blocks(body)
    ar_req = None
    iocrs: list[blocks.IocrRequest] = []
    alarm = None
    expected: list[blocks.ExpectedSubmodule] = []
    for btype, b in parts:
        if btype == blocks.BLOCK_AR_REQ:
            ar_req = blocks.ArRequest.unpack(b)
        elif btype == blocks.BLOCK_IOCR_REQ:
            iocrs.append(blocks.IocrRequest.unpack(b))
        elif btype == blocks.BLOCK_ALARM_CR_REQ:
            alarm = blocks.AlarmCrRequest.unpack(b)
        elif btype == blocks.BLOCK_EXPECTED_SUBMODULE:
            expected += blocks.expected_submodules(b)
    if ar_req is None:
        return _refuse(dev, addr, "Connect without an ARBlockReq", 1, 0), b""
    inputs = [c for c in iocrs if c.iocr_type == blocks.IOCR_INPUT]
    outputs = [c for c in iocrs if c.iocr_type == blocks.IOCR_OUTPUT]
    if ar_req.ar_type != 0x0001 or len(inputs) != 1 or len(outputs) != 1 or alarm is None:
        return _refuse(dev, addr, "only an IOCARSingle with one input IOCR, one output "
                       "IOCR and an AlarmCR is served", 1, 4), b""
    if dev.ar is not None and dev.ar.request.ar_uuid != ar_req.ar_uuid:
        return _refuse(dev, addr, "an AR is already open", 1, 5), b""
    for cr in (inputs[0], outputs[0]):
        if cr.properties & 0x0F != 1:
            return _refuse(dev, addr, f"IOCR {cr.reference}: only RT_CLASS_1", 2, 4), b""
        if cr.cycle_us < dev.min_cycle_us:
            return _refuse(dev, addr, f"IOCR {cr.reference}: cycle {cr.cycle_us / 1000} ms "
                           f"is below {dev.min_cycle_us / 1000} ms", 2, 8), b""
        if not cr.data_hold_factor >= 1 or cr.data_length > 1440:
            return _refuse(dev, addr, f"IOCR {cr.reference}: bad data hold factor or "
                           "length", 2, 26), b""
    diff = _diff(expected)
    in_id = inputs[0].frame_id if fr.FRAME_ID_RTC1_MIN <= inputs[0].frame_id <= \
        fr.FRAME_ID_RTC1_MAX else 0xC001
    out_id = 0xC000 + 0x100 + (outputs[0].reference & 0xFF)
    mac = ar_req.initiator_mac
    # diagnosis alarms go low priority (frame id 0xFE01), one in flight, RTA retries
    alarm_cr = AlarmCr(mac, dev.identity.mac, alarm.local_reference,
                       dev.device_alarm_ref, high=False,
                       timeout_s=max(alarm.timeout_factor, 1) * 0.1,
                       retries=min(max(alarm.retries, 3), 15))
    ar = Ar(ar_req, mac, (addr[0], rpc.RPC_PORT), inputs[0], outputs[0], in_id, out_id,
            alarm_cr, next_send=now, connected_at=now)
    dev.ar = ar
    dev.stats.connects += 1
    if diff:
        dev.stats.module_diffs += 1
    dev.output_image = bytes(layout.OUTPUT_SIZE)
    out.events.append(Event("connected", f"AR from {addr[0]} ({ar_req.station_name!r}), "
                            f"cycle {inputs[0].cycle_us / 1000:g} ms, data hold "
                            f"{ar.hold_s * 1000:g} ms"
                            + (f", {len(diff)} submodules differ" if diff else "")))
    body_out = (ar_req.response(dev.identity.mac) + inputs[0].response(in_id)
                + outputs[0].response(out_id) + alarm.response(dev.device_alarm_ref))
    if diff:
        body_out += blocks.module_diff(diff)
    return 0, body_out


def _diff(expected: list[blocks.ExpectedSubmodule]
          ) -> list[tuple[int, int, int, int, int, int, int]]:
    rows = []
    for e in expected:
        real = mod.find(e.slot, e.subslot) if e.api == mod.API else None
        if real is None:
            rows.append((e.api, e.slot, 0, blocks.MODULE_NO, e.subslot, 0, blocks.SUBMODULE_NO))
        elif real.module_ident != e.module_ident:
            rows.append((e.api, e.slot, real.module_ident, blocks.MODULE_WRONG, e.subslot,
                         real.submodule_ident, blocks.SUBMODULE_WRONG))
        elif (real.submodule_ident != e.submodule_ident
              or real.input_length != e.input_length
              or real.output_length != e.output_length):
            rows.append((e.api, e.slot, real.module_ident, blocks.MODULE_PROPER, e.subslot,
                         real.submodule_ident, blocks.SUBMODULE_WRONG))
    return rows


def _refuse(dev: Device, addr: tuple[str, int], text: str, code1: int, code2: int) -> int:
    dev.stats.refused_connects += 1
    dev.bad(f"Connect from {addr[0]} refused: {text}")
    return rpc.connect_error(code1, code2)


def owns(dev: Device, ar_uuid: bytes, session: int | None = None) -> bool:
    return dev.ar is not None and dev.ar.request.ar_uuid == ar_uuid and (
        session is None or dev.ar.request.session_key == session)


def control(dev: Device, body: bytes, addr: tuple[str, int], now: float,
            out: Out) -> tuple[int, bytes]:
    btype, b = blocks.split_blocks(body)[0]
    ctl = blocks.Control.unpack(btype, b)
    if not owns(dev, ctl.ar_uuid, ctl.session_key):
        dev.bad(f"Control from {addr[0]} for an unknown AR")
        return rpc.pnio_status(0xDD, 0x81, 0x3F, 0x05), b""  # IODControlRes, unknown AR
    assert dev.ar is not None
    if btype == blocks.BLOCK_PRM_END and ctl.command == blocks.CMD_PRM_END:
        dev.ar.phase = "ready"
        dev.ar.app_ready_at = now  # ApplicationReady goes out on the next tick
    elif btype == blocks.BLOCK_PRM_BEGIN and ctl.command == blocks.CMD_PRM_BEGIN:
        dev.ar.phase = "parameter"
    elif btype == blocks.BLOCK_RELEASE:
        return release(dev, body, addr, now, out)
    else:
        return rpc.pnio_status(0xDD, 0x81, 0x3F, 0x06), b""
    reply = blocks.Control(btype | blocks.RESPONSE_BIT, ctl.ar_uuid, ctl.session_key,
                           blocks.CMD_DONE)
    return 0, reply.pack()


def release(dev: Device, body: bytes, addr: tuple[str, int], now: float,
            out: Out) -> tuple[int, bytes]:
    btype, b = blocks.split_blocks(body)[0]
    ctl = blocks.Control.unpack(btype, b)
    if btype != blocks.BLOCK_RELEASE or not owns(dev, ctl.ar_uuid, ctl.session_key):
        dev.bad(f"Release from {addr[0]} for an unknown AR")
        return rpc.pnio_status(0xDE, 0x81, 0x3F, 0x05), b""
    dev.stats.releases += 1
    end(dev, out, Event("released", f"AR released by {addr[0]}"))
    return 0, blocks.Control(btype | blocks.RESPONSE_BIT, ctl.ar_uuid, ctl.session_key,
                             blocks.CMD_DONE).pack()


def end(dev: Device, out: Out, event: Event) -> None:
    dev.ar = None
    dev.output_image = bytes(layout.OUTPUT_SIZE)
    out.events.append(event)


def app_ready_request(ar: Ar) -> tuple[bytes, tuple[str, int]]:
    ctl = blocks.Control(blocks.BLOCK_APP_READY, ar.request.ar_uuid, ar.request.session_key,
                         blocks.CMD_APP_READY).pack()
    ndr = rpc.Ndr(len(ctl), ctl, len(ctl)).pack(True, response=False)
    head = rpc.RpcHeader(rpc.REQUEST, uuid.UUID(bytes=ar.request.initiator_object),
                         rpc.IFACE_CONTROLLER, ar.app_ready_activity, ar.app_ready_tries,
                         rpc.OP_CONTROL, len(ndr), True)
    return head.pack() + ndr, ar.controller_addr


def app_ready_confirmed(dev: Device, head: rpc.RpcHeader, body: bytes, now: float,
                        out: Out) -> None:
    ar = dev.ar
    if ar is None or head.activity != ar.app_ready_activity or ar.phase != "ready":
        return
    ndr = rpc.Ndr.unpack(body, head.little)
    if ndr.first != 0:
        dev.bad(f"ApplicationReady refused by the controller: 0x{ndr.first:08x}")
        return
    ar.phase = "data"
    out.events.append(Event("running", "ApplicationReady confirmed: data exchange"))
    for error_type in dev.diagnoses.values():  # what is down now, for the new AR
        out.frames += ar.alarm.diagnosis(True, error_type, now)
