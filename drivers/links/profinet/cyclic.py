"""The cyclic data of the IO AR (RT_CLASS_1, IEC 61158-6-10): the controller's output frames
read into the layout's OUTPUT block, the input frames' phase kept after them, and the input
frame built from the layout's INPUT block. Sans-I/O like the rest of the device: the clock is
passed in.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from .. import layout
from . import frames as fr
from . import modules as mod
from .state import Ar, Out

if TYPE_CHECKING:
    from .device import Device

REALIGN_AFTER: Final = 8  # output frames off the input phase in a row before it moves


def receive_output(dev: Device, eth: fr.Ethernet, frame_id: int, now: float, out: Out) -> None:
    """An RT frame of the output IOCR: the controller's outputs whose IOPS is good, into the
    output image (``out.output`` when it changed); a frame marked invalid leaves it as it is."""
    ar = dev.ar
    if ar is None or frame_id != ar.output_frame_id or eth.src != ar.controller_mac:
        return
    frame = fr.RtFrame.unpack(eth.payload, ar.output_cr.data_length)
    dev.stats.frames_in += 1
    if not frame.data_status & fr.DATA_STATUS_VALID:
        return
    running = bool(frame.data_status & fr.DATA_STATUS_RUN)
    keep_phase(ar, now, dev.input_phase_s)
    ar.last_output = now
    image = bytearray(layout.OUTPUT_SIZE)
    if running:
        for obj in ar.output_cr.data:
            sub = mod.find(obj.slot, obj.subslot)
            if sub is None or not sub.output_length:
                continue
            lo, n = sub.output
            end = obj.offset + n
            if end >= len(frame.c_sdu):
                raise fr.FrameError(f"IO data of slot {obj.slot} runs past the C_SDU")
            if frame.c_sdu[end] & fr.IOXS_GOOD:  # the controller's IOPS
                image[lo:lo + n] = frame.c_sdu[obj.offset:end]
    data = bytes(image)
    if data != dev.output_image:
        dev.output_image = data
        out.output = data


def keep_phase(ar: Ar, now: float, input_phase_s: float | None) -> None:
    """Keep the input frames ``input_phase_s`` (None: half the cycle) after the controller's
    output frames (FrameSendOffset "best effort" leaves the phase in the cycle to the
    device): what the station answers to an output frame within that time leaves with the
    next input frame, not up to a cycle later. The first output frame sets the phase; it
    moves again only after REALIGN_AFTER frames in a row came more than a quarter cycle off
    it (a clock drift, the controller's restart), not with one late frame."""
    period = ar.input_period_s
    phase = period / 2 if input_phase_s is None else input_phase_s
    want = now + min(phase, period / 2)
    off = (ar.next_send - want) % period
    if ar.last_output is not None and min(off, period - off) <= period / 4:
        ar.off_phase = 0
        return
    ar.off_phase += 1
    if ar.last_output is None or ar.off_phase >= REALIGN_AFTER:
        ar.next_send, ar.off_phase = want, 0
        ar.realigned += 1


def input_frame(ar: Ar, input_image: bytes, mac: bytes) -> bytes:
    """The next input frame: ``input_image`` (the layout's INPUT block) into the input
    IOCR's submodules with good IOPS and IOCS; ``mac`` is the device's."""
    sdu = bytearray(ar.input_cr.data_length)
    for obj in ar.input_cr.data:
        sub = mod.find(obj.slot, obj.subslot)
        n = 0
        if sub is not None and sub.input_length:
            lo, n = sub.input
            sdu[obj.offset:obj.offset + n] = input_image[lo:lo + n]
        if obj.offset + n < len(sdu):
            sdu[obj.offset + n] = fr.IOXS_GOOD  # our IOPS
    for obj in ar.input_cr.iocs:
        if obj.offset < len(sdu):
            sdu[obj.offset] = fr.IOXS_GOOD  # our IOCS for the controller's data
    ar.cycle = (ar.cycle + ar.input_cr.send_clock_factor * ar.input_cr.reduction_ratio) \
        & 0xFFFF
    rt = fr.RtFrame(ar.input_frame_id, bytes(sdu), ar.cycle, fr.DATA_STATUS_GOOD)
    return fr.Ethernet(ar.controller_mac, mac, fr.ETHERTYPE_PN, rt.pack(),
                       vlan_tci=0xC000).pack()
