"""The PLC twin's Modbus/TCP port: a pymodbus client reading the input registers (or their
holding-register mirror) and writing the holding registers, as a PLC's Modbus client does."""

from __future__ import annotations

from pymodbus.client import AsyncModbusTcpClient

from .. import layout as r
from ..layout import INPUT, OUTPUT, ByteOrder, WordOrder
from ..twin import PlcTwin, PlcTwinError
from .server import HR_MIRROR


class ModbusTwin(PlcTwin):
    """A PLC twin on Modbus/TCP; ``client`` is its pymodbus client, for tests that send a
    request the program itself does not."""

    port: ModbusPort

    @property
    def client(self) -> AsyncModbusTcpClient:
        return self.port.client


class ModbusPort:
    """:class:`~drivers.links.twin.PlcPort` over Modbus/TCP (registers are big-endian words)."""

    byte_order = ByteOrder.BIG

    def __init__(self, host: str, port: int, *, word_order: WordOrder = WordOrder.ABCD,
                 device_id: int = 1, use_mirror: bool = False) -> None:
        self.client = AsyncModbusTcpClient(host, port=port, timeout=2, retries=0, reconnect_delay=0)
        self.word_order = WordOrder(word_order)
        self.device_id = device_id
        self.use_mirror = use_mirror  # read the holding-register mirror (fc 3) instead of fc 4

    async def connect(self) -> None:
        if not await self.client.connect():
            raise PlcTwinError(f"PLC twin: cannot connect to {self.client.comm_params.host}")

    async def read_inputs(self) -> bytes:
        if self.use_mirror:
            rr = await self.client.read_holding_registers(
                HR_MIRROR, count=r.IR_COUNT, device_id=self.device_id)
        else:
            rr = await self.client.read_input_registers(
                0, count=r.IR_COUNT, device_id=self.device_id)
        if rr.isError():
            raise PlcTwinError(f"PLC twin: status read answered {rr}")
        return INPUT.to_bytes(rr.registers, self.byte_order)

    async def write_outputs(self, offset: int, data: bytes) -> None:
        words = OUTPUT.to_words(data, self.byte_order, start=offset // 2)
        rr = await self.client.write_registers(offset // 2, words, device_id=self.device_id)
        if rr.isError():
            raise PlcTwinError(f"PLC twin: write of {len(words)} at {offset // 2} answered {rr}")

    def close(self) -> None:
        self.client.close()

    def abort(self) -> None:
        transport = self.client.ctx.transport
        if transport is not None:
            transport.abort()  # type: ignore[attr-defined]


def modbus_twin(host: str, port: int, *, word_order: WordOrder = WordOrder.ABCD,
                device_id: int = 1, use_mirror: bool = False, poll_s: float = 0.0) -> ModbusTwin:
    """A PLC twin on Modbus/TCP."""
    return ModbusTwin(ModbusPort(host, port, word_order=word_order, device_id=device_id,
                              use_mirror=use_mirror), poll_s=poll_s)
