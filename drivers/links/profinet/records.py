"""Read and Write of records (IEC 61158-6-10, IODReadReq / IODWriteReq): I&M0..4 and
RealIdentificationData read, I&M1..4 written and kept, the parameter records a controller
writes in its parameter phase kept and read back. Functions over the
:class:`~.device.Device`'s state; each answers (PNIO status, body).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from . import blocks, rpc
from . import im as imr
from . import modules as mod
from .dcp import Event
from .relation import owns
from .state import Out

if TYPE_CHECKING:
    from .device import Device

log = logging.getLogger(__name__)


def read(dev: Device, body: bytes, addr: tuple[str, int], now: float,
         out: Out) -> tuple[int, bytes]:
    req = blocks.RecordRequest.unpack(body)
    data = _record(dev, req)
    if data is None:
        # ErrorCode 0xDE IODReadRes, ErrorDecode 0x80 PNIORW, access: invalid index
        return rpc.pnio_status(0xDE, 0x80, 0xB0, 0x00), req.response(0)
    return 0, req.response(len(data)) + data


def _record(dev: Device, req: blocks.RecordRequest) -> bytes | None:
    if req.index == 0xAFF0 and req.slot == 0:
        return imr.im0(dev.identity)
    if req.index in imr.RECORDS and req.slot == 0:
        return imr.block(imr.RECORDS[req.index], dev.im[req.index])
    if req.index == 0xF000:
        return imr.real_identification()
    return dev.records.get((req.slot, req.subslot, req.index))


def write(dev: Device, body: bytes, addr: tuple[str, int], now: float,
          out: Out) -> tuple[int, bytes]:
    req = blocks.RecordRequest.unpack(body)
    sub = mod.find(req.slot, req.subslot)
    # user records (0..0x7FFF) and the port/interface records a controller writes in its
    # parameter phase (0x8000..0xAFFF: PDPortDataCheck, PDInterfaceAdjust, ...) are kept
    if not owns(dev, req.ar_uuid) or sub is None or req.index >= 0xB000:
        # IODWriteRes, PNIORW, access: invalid slot/subslot or index
        status = rpc.pnio_status(0xDF, 0x80, 0xB2 if sub is None else 0xB0, 0)
        return status, req.response(0, status)
    if req.index in imr.RECORDS:
        return _write_im(dev, req, addr, out)
    dev.records[(req.slot, req.subslot, req.index)] = req.data
    return 0, req.response(len(req.data))


def _write_im(dev: Device, req: blocks.RecordRequest, addr: tuple[str, int],
              out: Out) -> tuple[int, bytes]:
    record = imr.RECORDS[req.index]
    data, code1 = imr.written(record, req.data) if req.slot == 0 else (None, 0xB2)
    if data is None:
        # IODWriteRes, PNIORW, access: write length error / invalid parameter / slot
        status = rpc.pnio_status(0xDF, 0x80, code1, 0)
        text = (f"I&M{record.number} Write from {addr[0]} refused: {len(req.data)} "
                f"bytes, ErrorCode1 0x{code1:02X}")
        dev.stats.last_errors = [*dev.stats.last_errors[-9:], text]
        log.info("profinet: %s", text)
        return status, req.response(0, status)
    dev.im[req.index] = data
    out.im_changed = True
    out.events.append(Event("im_written", f"I&M{record.number} written by {addr[0]}"))
    return 0, req.response(len(req.data))
