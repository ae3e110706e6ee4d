"""The real Modbus/TCP server on loopback, driven by the PLC twin: flows and every error path."""

# The `plc` fixture is imported from plc_peers (tests/drivers has no conftest of ours), so the
# test arguments that use it look like redefinitions to ruff.
# ruff: noqa: F811

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import pytest
from plc_peers import (  # noqa: F401
    ArithmeticHandler,
    ServerFactory,
    cfg,
    expected_outcome,
    plc,
    published_offset,
)
from pymodbus.client import AsyncModbusTcpClient

from drivers.links import codecs as c
from drivers.links import layout as r
from drivers.links.base import LinkOutcome, LinkRequest
from drivers.links.modbus import (
    Command,
    Control,
    ErrorCode,
    State,
    Status,
    WordOrder,
)
from drivers.links.modbus.server import HR_MIRROR
from drivers.links.modbus.twin import modbus_twin
from drivers.links.twin import PlcStatus
from mvpose_core.reasons import Reason
from mvpose_core.transforms import (
    RobotConvention,
    compose,
    from_robot,
    invert,
    make_transform,
    rotvec_to_matrix,
    to_robot,
    transform_error,
)
from server.loopback import detach_twin


async def until(predicate, timeout: float = 3.0) -> None:
    """Poll a server-side condition with a deadline."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached before the deadline"
        await asyncio.sleep(0.005)


def check_result(answer: PlcStatus, trigger_id: int) -> None:
    want = expected_outcome(trigger_id)
    sent = published_offset(trigger_id)
    assert answer.trigger_id == trigger_id
    assert answer.has(Status.RESULT_VALID)
    assert answer.has(Status.RESULT_OK) == (want.result_code == 0)
    assert answer.result_code == want.result_code
    counts = [round(v * s) for v, s in zip(sent, (1e3, 1e3, 1e3, 1e4, 1e4, 1e4), strict=True)]
    assert list(answer.offset_counts) == counts
    assert np.allclose(answer.offset_float, sent, rtol=1e-6, atol=1e-5)
    assert answer.sigma_counts == (
        round(want.sigma_trans_mm * 1e3),
        round(want.sigma_rot_deg * 1e4),
    )


@pytest.mark.parametrize(
    ("order", "mirror"), [(WordOrder.ABCD, False), (WordOrder.CDAB, False), (WordOrder.CDAB, True)]
)
async def test_fixed_station_flow(plc: ServerFactory, order: WordOrder, mirror: bool) -> None:
    handler = ArithmeticHandler()
    server, twin = await plc(handler, cfg(word_order=order), use_mirror=mirror)
    status = await twin.read_status()
    assert status.state is State.READY and status.recipe == 1
    assert status.test_float == pytest.approx(123.45, abs=1e-5) and status.test_int == r.TEST_INT
    assert status.convention_code == RobotConvention.FANUC.code
    ids = [7, 26, 0xFFFF_FFFE]  # 26: a NOK result; the last one needs both words
    for n, tid in enumerate(ids, start=1):
        t = time.perf_counter()
        answer = await twin.cycle(tid, part_id=f"VIN{tid}")
        whole = time.perf_counter() - t
        check_result(answer, tid)
        assert answer.result_id == n
        # trigger → answer is inside the cycle, which also waits for READY and the ACK
        assert 0.0 < twin.last_answer_s < whole
    assert [q.trigger_id for q in handler.requests] == ids
    assert handler.requests[0].part_id == "VIN7" and handler.requests[0].view_index == 0
    assert server.stats.handshake.results == 3 and server.stats.handshake.missed_triggers == 0


class ViewHandler(ArithmeticHandler):
    """A robot-mounted rig's pipeline on real mvpose_core transforms: each view reports the part
    pose seen from the flange pose the PLC sent (ABB's full quaternion: the link restored q1);
    after the last view the offset is the mean part displacement against the reference, in the
    recipe's convention (ABB: 7 values; the link sends the PLC form)."""

    def __init__(self, T_rf_from_pf: np.ndarray, T_rf_from_pf0: np.ndarray, n_views: int) -> None:
        super().__init__()
        self.T_rf_from_pf = T_rf_from_pf
        self.T_rf_from_pf0 = T_rf_from_pf0
        self.n_views = n_views
        self.seen: list[np.ndarray] = []
        self.resets = 0

    async def measure(self, req: LinkRequest) -> LinkOutcome:
        assert req.robot_pose is not None and len(req.robot_pose) == 7
        T_rf_from_gf = from_robot(req.robot_pose, "abb")
        T_gf_from_pf = compose(invert(T_rf_from_gf), self.T_rf_from_pf)  # what the rig "sees"
        self.seen.append(compose(T_rf_from_gf, T_gf_from_pf))
        if req.view_index < self.n_views:
            return LinkOutcome(0, 0, views_done=len(self.seen), final=False)
        T_pf0_from_pf = compose(invert(self.T_rf_from_pf0), self.seen[-1])
        offset = tuple(to_robot(T_pf0_from_pf, "abb"))
        views = len(self.seen)
        self.seen = []
        return LinkOutcome(0, self.next_id(), offset, 0.1, 0.01, 3.0, views_done=views)

    async def reset(self) -> None:
        self.resets += 1
        self.seen = []

    def convention(self) -> RobotConvention:
        return RobotConvention.ABB


async def test_robot_mounted_flow_with_flange_poses(plc: ServerFactory) -> None:
    rng = np.random.default_rng(11)
    T_ref = make_transform(rotvec_to_matrix([0.0, 0.0, 0.3]), [1500.0, 200.0, 800.0])
    T_true_offset = make_transform(rotvec_to_matrix(rng.normal(0, 0.01, 3)), rng.normal(0, 5, 3))
    handler = ViewHandler(compose(T_ref, T_true_offset), T_ref, n_views=2)
    _, twin = await plc(handler, cfg(word_order=WordOrder.CDAB))
    flange = [
        make_transform(rotvec_to_matrix([np.pi, 0, a]), [1200.0, y, 1400.0])
        for a, y in ((0.1, -400), (-0.1, 400))
    ]
    for view, T in enumerate(flange, start=1):
        plc_pose = c.pose_to_plc(to_robot(T, "abb"), "abb")
        counts = [round(v * s) for v, s in zip(plc_pose, c.int_scales("abb"), strict=True)]
        answer = await twin.cycle(100 + view, view_index=view, pose_counts=counts)
        assert answer.views_done == view and answer.trigger_id == 100 + view
        if view < len(flange):
            assert answer.has(Status.VIEW_DONE) and not answer.has(Status.RESULT_VALID)
            assert answer.result_id == 0
    assert answer.has(Status.RESULT_VALID | Status.RESULT_OK) and answer.result_id == 1
    assert answer.convention_code == RobotConvention.ABB.code
    # Decode the way a PLC does (1e-6 quaternion counts, q1 recovered) and compare with truth.
    scales = c.int_scales("abb")
    from_ints = [n / s for n, s in zip(answer.offset_counts, scales, strict=True)]
    for six in (from_ints, answer.offset_float):
        T_got = from_robot(c.plc_to_pose(six, "abb"), "abb")
        deg, mm = transform_error(T_got, T_true_offset)
        assert deg < 1e-3 and mm < 2e-3  # flange pose on the wire: 1 µm and 1e-6 quaternion counts


async def test_a_concurrent_reader_never_sees_a_torn_result_block(plc: ServerFactory) -> None:
    server, twin = await plc(config=cfg(word_order=WordOrder.CDAB))
    spy = await modbus_twin("127.0.0.1", server.port, word_order=WordOrder.CDAB).connect()
    snapshots: list[PlcStatus] = []
    running = True

    async def watch() -> None:
        while running:
            snapshots.append(await spy.read_status())

    watcher = asyncio.create_task(watch())
    trigger_of_result = {}
    try:
        for tid in range(500, 800):
            answer = await twin.cycle(tid)
            trigger_of_result[answer.result_id] = tid
    finally:
        running = False
        await watcher
        spy.close()
    seen = [s for s in snapshots if s.result_id]
    assert len(seen) > 100
    for snap in seen:
        tid = trigger_of_result[snap.result_id]
        sent = published_offset(tid)
        assert snap.result_code == expected_outcome(tid).result_code
        assert snap.offset_counts[0] == round(sent[0] * 1e3)
        assert snap.offset_counts[5] == round(sent[5] * 1e4)
        assert snap.offset_float[2] == pytest.approx(sent[2])


async def test_commands_select_recipe_teach_and_refusals(plc: ServerFactory) -> None:
    handler = ArithmeticHandler()
    server, twin = await plc(handler)
    done = await twin.command(Command.SELECT_RECIPE, 2)
    assert done.has(Status.COMMAND_DONE) and done.command_result == 0 and done.recipe == 2
    assert (await twin.read_status()).convention_code == RobotConvention.ABB.code
    failed = await twin.command(Command.SELECT_RECIPE, 9)
    assert failed.has(Status.COMMAND_FAILED) and failed.command_result == 3 and failed.recipe == 2
    done = await twin.command(Command.TEACH_REFERENCE)
    assert done.has(Status.COMMAND_DONE) and handler.teach_requests == 1
    failed = await twin.command(77)
    assert failed.command_result == Reason.UNKNOWN_COMMAND

    handler.gate = asyncio.Event()  # keep a measurement running
    await twin.write_trigger(5)
    await until(lambda: server.state is State.SINGLE_EXECUTION)
    busy = await twin.command(Command.RESET)
    assert busy.has(Status.COMMAND_FAILED) and busy.command_result == Reason.BUSY
    handler.gate.set()
    answer = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), what="result")
    assert answer.trigger_id == 5 and answer.result_id == 1


async def test_missed_trigger_while_busy(plc: ServerFactory) -> None:
    handler = ArithmeticHandler()
    handler.gate = asyncio.Event()
    server, twin = await plc(handler)
    await twin.write_trigger(1)
    await twin.wait_for(lambda s: s.has(Status.TRIGGER_ACK | Status.BUSY), what="ack")
    await twin.set_control(twin.control & ~Control.TRIGGER)
    await twin.write_trigger(2)
    missed = await twin.wait_for(lambda s: s.has(Status.MISSED_TRIGGER), what="missed trigger")
    assert missed.trigger_id == 1 and missed.has(Status.BUSY)
    handler.gate.set()
    answer = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), what="result")
    assert answer.trigger_id == 1 and answer.result_id == 1
    await twin.set_control((twin.control & ~Control.TRIGGER) | Control.RESULT_ACK)
    check_result(await twin.cycle(3), 3)
    assert [q.trigger_id for q in handler.requests] == [1, 3]
    assert server.stats.handshake.missed_triggers == 1 and server.stats.handshake.results == 2


async def test_held_trigger_forces_reset(plc: ServerFactory) -> None:
    server, twin = await plc(config=cfg(trigger_hold_s=0.2))
    await twin.write_trigger(8)
    result = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), what="result")
    check_result(result, 8)
    held = await twin.wait_for(lambda s: s.has(Status.ERROR), what="held-trigger error")
    assert held.error_code == ErrorCode.TRIGGER_HELD and held.state is State.ERROR
    assert not held.has(Status.TRIGGER_ACK) and held.has(Status.RESULT_VALID)
    await twin.set_control(twin.control | Control.ERROR_RESET)
    still = await twin.read_status()
    assert still.has(Status.ERROR)  # the trigger is still high
    await twin.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
    await twin.reset_error()
    check_result(await twin.cycle(9), 9)
    assert server.stats.handshake.held_triggers == 1


async def test_watchdog_on_lost_heartbeat(plc: ServerFactory) -> None:
    handler = ArithmeticHandler()
    server, twin = await plc(handler, cfg(watchdog_s=0.2, tick_s=0.02))
    tripped = await twin.wait_for(lambda s: s.has(Status.ERROR), timeout=3, what="watchdog")
    assert tripped.error_code == ErrorCode.WATCHDOG and not tripped.has(
        Status.ONLINE | Status.READY
    )
    beat = tripped.heartbeat
    alive = await twin.wait_for(lambda s: s.heartbeat != beat, what="server heartbeat")
    assert alive.has(Status.ERROR)  # the server keeps beating while in Error
    await twin.reset_error()
    assert handler.resets == 1
    check_result(await twin.cycle(4), 4)


async def test_heartbeat_task_keeps_the_watchdog_quiet(plc: ServerFactory) -> None:
    server, twin = await plc(config=cfg(watchdog_s=0.15, tick_s=0.01))
    beating = asyncio.create_task(twin.keep_alive(0.02))
    try:
        ticks = server.machine.image[r.IR_HEARTBEAT]
        await until(lambda: (server.machine.image[r.IR_HEARTBEAT] - ticks) % 65536 > 40)
        check_result(await twin.cycle(12), 12)
        assert server.stats.handshake.watchdog_trips == 0 and server.state is State.READY
    finally:
        beating.cancel()
    with pytest.raises(asyncio.CancelledError):
        await beating
    await until(lambda: server.machine.error is ErrorCode.WATCHDOG)


async def test_heartbeat_task_ends_on_stop_without_a_cancel(plc: ServerFactory) -> None:
    # On Python 3.11 a cancel can be lost inside pymodbus (asyncio.wait_for, CPython gh-86296);
    # the stop flag alone must end the heartbeat, or a disconnecting PLC twin hangs for ever.
    server, twin = await plc(config=cfg(watchdog_s=0.15, tick_s=0.01))
    beating = asyncio.create_task(twin.keep_alive(0.02))
    ticks = twin.heartbeat
    await until(lambda: twin.heartbeat - ticks >= 3)
    twin.stop_keep_alive()
    await asyncio.wait_for(beating, 2.0)
    assert beating.done() and not beating.cancelled()
    stopped_at = twin.heartbeat
    await until(lambda: server.machine.error is ErrorCode.WATCHDOG)
    assert twin.heartbeat == stopped_at


class RecordingHandler(ArithmeticHandler):
    """Numbers its results like a store whose last record is 500."""

    def __init__(self) -> None:
        super().__init__()
        self.seq = 500


async def test_the_result_id_is_the_handlers_and_link_failures_are_recorded(
    plc: ServerFactory,
) -> None:
    handler = RecordingHandler()
    server, twin = await plc(handler, config=cfg(measure_timeout_s=0.2))
    await twin.wait_for(lambda s: s.has(Status.READY), 2.0, "READY")
    status = await twin.cycle(71)
    check_result(status, 71)
    assert status.result_id == 501 == server.machine.result_id
    handler.gate = asyncio.Event()  # never set: the link's backstop answers TIMEOUT
    status = await twin.cycle(72, timeout=3.0)
    assert status.result_code == Reason.TIMEOUT
    assert status.result_id == 502  # the failure's own record, not a counter of the link
    assert handler.failures and handler.failures[0][:2] == (72, int(Reason.TIMEOUT))


async def test_detaching_a_twin_leaves_no_request_unanswered(
    plc: ServerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    # A heartbeat every 0.5 ms: a write is in flight at almost any moment of the detach. It must
    # end by the stop, which lets that write finish, not by a cancel: a cancelled write leaves
    # the server answering a closed connection, which pymodbus logs as an error with a dump of
    # the last frames (seen with the twin in a process of its own, bench/twin_process.py).
    server, _ = await plc()
    for _ in range(5):
        twin = await modbus_twin("127.0.0.1", server.port).connect()
        beat = asyncio.create_task(twin.keep_alive(0.0005))
        await until(lambda t=twin: t.heartbeat >= 3)
        await detach_twin(twin, beat)
        assert beat.done() and not beat.cancelled()
    await until(lambda: server.stats.writes >= 15)
    await asyncio.sleep(0)  # let the server handle anything still buffered
    errors = [rec.getMessage() for rec in caplog.records if rec.levelno >= logging.ERROR]
    assert errors == []


async def test_deadline_and_exception_become_result_codes(plc: ServerFactory) -> None:
    handler = ArithmeticHandler()
    server, twin = await plc(handler, cfg(measure_timeout_s=0.2))
    handler.gate = asyncio.Event()  # never set: the measurement hangs
    late = await twin.cycle(1)
    assert late.result_code == Reason.TIMEOUT and not late.has(Status.RESULT_OK)
    assert late.result_id == 1 and late.processing_ms >= 190
    handler.gate, handler.fail = None, True
    broken = await twin.cycle(2)
    assert broken.result_code == Reason.HANDLER_FAILED and broken.result_id == 2
    handler.fail = False
    check_result(await twin.cycle(3), 3)
    assert handler.resets == 2  # each failure dropped any half-done view sequence
    assert server.stats.timeouts == 1 and server.stats.handler_errors == 1


class StartsWhenCalled(ArithmeticHandler):
    """A pipeline whose ``measure`` starts the work in the call and returns a future (as the
    station runtime's does); the test completes each future by hand."""

    def __init__(self) -> None:
        super().__init__()
        self.pending: list[asyncio.Future[LinkOutcome]] = []
        self.write: asyncio.Task[None] | None = None  # the PLC's TRIGGER write, when watched
        self.write_answered: list[bool] = []  # whether it was answered when measure() came

    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:  # type: ignore[override]
        self.requests.append(request)
        if self.write is not None:
            self.write_answered.append(self.write.done())
        if self.fail:
            raise RuntimeError(f"trigger thread gone at trigger {request.trigger_id}")
        fut: asyncio.Future[LinkOutcome] = asyncio.get_running_loop().create_future()
        self.pending.append(fut)
        return fut


async def test_a_trigger_starts_its_measurement_before_the_write_is_answered(
    plc: ServerFactory,
) -> None:
    handler = StartsWhenCalled()
    server, twin = await plc(handler, cfg(measure_timeout_s=0.2))
    await twin.wait_for(lambda s: s.has(Status.READY), 2.0, "READY")
    handler.write = asyncio.create_task(twin.write_trigger(61))
    await handler.write
    # measure() ran while the write was still waiting for its response, not passes later.
    assert handler.write_answered == [False] and len(handler.pending) == 1
    handler.pending[0].set_result(expected_outcome(61, handler.next_id()))
    status = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), 2.0, "result")
    check_result(status, 61)
    await twin.set_control((twin.control & ~Control.TRIGGER) | Control.RESULT_ACK)
    # A measurement past the deadline: its future is cancelled, the PLC gets TIMEOUT.
    late = await twin.cycle(62)
    assert late.result_code == Reason.TIMEOUT and handler.pending[1].cancelled()
    # measure() raising in the call itself: an INTERNAL_ERROR result, the link carries on.
    handler.fail = True
    broken = await twin.cycle(63)
    assert broken.result_code == Reason.HANDLER_FAILED and broken.result_id == 3
    assert server.stats.handler_errors == 1 and server.stats.timeouts == 1
    assert handler.resets == 2  # each failure dropped any half-done view sequence


async def test_disconnect_mid_handshake_loses_nothing(plc: ServerFactory) -> None:
    handler = ArithmeticHandler()
    handler.gate = asyncio.Event()
    server, twin = await plc(handler)
    await twin.write_trigger(41)
    await until(lambda: server.state is State.SINGLE_EXECUTION)
    twin.abort()  # PLC stop / pulled cable in the middle of the measurement
    handler.gate.set()
    await until(lambda: server.machine.result_id == 1)
    again = await modbus_twin("127.0.0.1", server.port).connect()
    try:
        again.control = Control.TRIGGER_ENABLE | Control.TRIGGER  # what the PLC still drives
        status = await again.read_status()
        check_result(status, 41)
        await again.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
        answer = await again.cycle(42)
        check_result(answer, 42)
        assert answer.result_id == 2
    finally:
        again.close()
    assert [q.trigger_id for q in handler.requests] == [41, 42]


async def test_read_write_multiple_writes_control_and_reads_the_mirror(plc: ServerFactory) -> None:
    server, twin = await plc()
    cl: AsyncModbusTcpClient = twin.client
    ids = c.encode_uint32(77, WordOrder.ABCD)
    trigger = [int(Control.TRIGGER_ENABLE | Control.TRIGGER), 500, 0, 0, *ids, 0]
    rr = await cl.readwrite_registers(
        read_address=HR_MIRROR, read_count=r.IR_COUNT, write_address=0, values=trigger
    )
    assert not rr.isError() and len(rr.registers) == r.IR_COUNT
    answer = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), what="result")
    check_result(answer, 77)
    release = [int(Control.TRIGGER_ENABLE | Control.RESULT_ACK), 501]
    deadline = time.monotonic() + 3
    while True:  # fc 23 as a combined "write control, poll status" step
        rr = await cl.readwrite_registers(
            read_address=HR_MIRROR, read_count=r.IR_COUNT, write_address=0, values=release
        )
        mirror = PlcStatus(tuple(rr.registers), WordOrder.ABCD)
        if mirror.has(Status.READY):
            break
        assert time.monotonic() < deadline
    assert mirror.regs[:1] + mirror.regs[2:] == tuple(
        server.input_registers()[:1] + server.input_registers()[2:]
    )
    assert mirror.result_id == 1 and not mirror.has(Status.RESULT_VALID)


async def test_exception_codes_for_requests_outside_the_map(plc: ServerFactory) -> None:
    server, twin = await plc()
    cl: AsyncModbusTcpClient = twin.client
    cases = [
        (cl.write_registers(r.HR_WRITABLE_COUNT, [1]), 2),  # past the PLC area
        (cl.write_registers(38, [1, 2, 3]), 2),  # straddles the end
        (cl.write_register(HR_MIRROR, 1), 2),  # the mirror is read-only
        (cl.read_input_registers(r.IR_COUNT, count=1), 2),
        (cl.read_holding_registers(60, count=2), 2),  # the gap between areas
        (cl.read_coils(0, count=1), 1),
        (cl.write_coil(0, True), 1),
        (cl.write_register(r.HR_CONTROL, 0x8000 | Control.TRIGGER_ENABLE), 3),  # reserved bit
    ]
    for request, code in cases:
        rr = await request
        assert rr.isError() and rr.exception_code == code, rr
    # pymodbus refuses unmapped addresses itself; the value check on the control word is ours.
    assert server.stats.rejected_requests >= 1
    assert (await twin.read_status()).state is State.READY  # nothing of it reached the handshake
    check_result(await twin.cycle(1), 1)


async def test_malformed_frames_and_abrupt_disconnects(plc: ServerFactory) -> None:
    server, twin = await plc()
    rng = np.random.default_rng(5)
    frames = [
        bytes(rng.integers(0, 256, 64, dtype=np.uint8)),
        b"\x00\x01\x00\x00\x00\x06\x01",  # truncated header
        b"\x00\x01\x00\x07\x00\x06\x01\x04\x00\x00\x00\x02",  # wrong protocol id
        b"\x00\x01\x00\x00\x00\x02\x01\x63",  # unknown function code 0x63
        b"\x00\x01\x00\x00\xff\xff\x01\x03" + b"\x00" * 16,  # length beyond the data
    ]
    for frame in frames:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(frame)
        await writer.drain()
        writer.transport.abort()
    check_result(await twin.cycle(1), 1)  # the server still answers the PLC


async def test_allowlist_refuses_other_addresses(plc: ServerFactory) -> None:
    server, twin = await plc(config=cfg(allowlist=("127.0.0.0/8",)))
    check_result(await twin.cycle(1), 1)

    closed, _ = await plc(config=cfg(allowlist=("10.20.30.40",)), connect=False)
    reader, writer = await asyncio.open_connection("127.0.0.1", closed.port)
    writer.write(b"\x00\x01\x00\x00\x00\x06\x01\x04\x00\x00\x00\x02")
    await writer.drain()
    assert await asyncio.wait_for(reader.read(100), 3) == b""  # closed without an answer
    writer.close()
    assert closed.stats.rejected_connections >= 1
