"""A simulated Modbus device: the server side of the codec over an in-memory data model.

``sim://`` answers from here in-process; ``mbtool serve`` grows from the same
model.  Requests are decoded by the same codec types the client encodes with,
so both sides read the spec the same way.
"""

from __future__ import annotations

from array import array
from collections.abc import Callable

from mbtool.codec.data_access import (
    BitsResponse,
    ReadCoils,
    ReadDiscreteInputs,
    ReadHoldingRegisters,
    ReadInputRegisters,
    RegistersResponse,
    WriteMultipleCoils,
    WriteMultipleRegisters,
    WriteMultipleResponse,
    WriteSingleCoil,
    WriteSingleRegister,
)
from mbtool.codec.framing import Frame, Framer
from mbtool.codec.pdu import (
    ExceptionCode,
    ExceptionResponse,
    Request,
    Response,
    decode_request,
    function_type,
)
from mbtool.errors import DecodeError, RequestError

TABLE_SIZE = 0x10000  # every table spans the whole 16-bit address space (spec §1)


class DataModel:
    """The four tables of spec §1."""

    def __init__(self) -> None:
        self.coils = bytearray(TABLE_SIZE)
        self.discrete_inputs = bytearray(TABLE_SIZE)
        self.holding_registers = array("H", bytes(2 * TABLE_SIZE))
        self.input_registers = array("H", bytes(2 * TABLE_SIZE))


def demo_model() -> DataModel:
    """The data ``sim://`` starts with, so a first read shows something (README lists it)."""
    model = DataModel()
    for i in range(100):
        model.holding_registers[i] = i
        model.input_registers[i] = 1000 + i
        model.coils[i] = i % 2 == 0
        model.discrete_inputs[i] = i % 3 == 0
    # A float32 21.5 (°C, say) at holding registers 100-101, big-endian words (ABCD),
    # and the same value word-swapped (CDAB) at 102-103, to try --type and --order on.
    model.holding_registers[100:104] = array("H", [0x41AC, 0x0000, 0x0000, 0x41AC])
    return model


class Device:
    """Answers request PDUs for a set of unit ids; unit 0 (broadcast) is applied, never answered."""

    def __init__(self, model: DataModel | None = None, units: frozenset[int] = frozenset({1})) -> None:
        self.model = model or DataModel()
        self.units = units
        self._handlers: dict[type[Request], Callable[[Request], Response]] = {
            ReadCoils: lambda r: self._read_bits(r, self.model.coils),
            ReadDiscreteInputs: lambda r: self._read_bits(r, self.model.discrete_inputs),
            ReadHoldingRegisters: lambda r: self._read_registers(r, self.model.holding_registers),
            ReadInputRegisters: lambda r: self._read_registers(r, self.model.input_registers),
            WriteSingleCoil: self._write_single_coil,
            WriteSingleRegister: self._write_single_register,
            WriteMultipleCoils: self._write_multiple_coils,
            WriteMultipleRegisters: self._write_multiple_registers,
        }

    # -- entry points ------------------------------------------------------------

    def answer_frame(self, event: Frame | object, framer: Framer) -> bytes | None:
        """The reply ADU to a framed request, or None (not a frame, not for us, broadcast)."""
        if not isinstance(event, Frame):
            return None  # a real slave ignores a frame with a bad checksum (spec §2)
        reply = self.handle(event.unit, event.pdu)
        if reply is None:
            return None
        return framer.build(event.unit, reply, event.transaction_id or 0)

    def handle(self, unit: int, pdu: bytes) -> bytes | None:
        """The reply PDU to a request PDU, or None when no reply is due."""
        if unit != 0 and unit not in self.units:
            return None
        reply = self._reply(pdu)
        return None if unit == 0 else reply.encode()

    def _reply(self, pdu: bytes) -> Response | ExceptionResponse:
        code = pdu[0] if pdu else 0
        try:
            request = decode_request(pdu)
        except RequestError as error:
            return ExceptionResponse(code, error.exception_code)
        except DecodeError:
            known = function_type(code) is not None
            return ExceptionResponse(
                code, ExceptionCode.ILLEGAL_DATA_VALUE if known else ExceptionCode.ILLEGAL_FUNCTION
            )
        handler = self._handlers.get(type(request))
        if handler is None:
            return ExceptionResponse(code, ExceptionCode.ILLEGAL_FUNCTION)
        try:
            return handler(request)
        except RequestError as error:
            return ExceptionResponse(code, error.exception_code)

    # -- the function codes ----------------------------------------------------------

    @staticmethod
    def _read_bits(request, table: bytearray) -> BitsResponse:
        bits = tuple(bool(b) for b in table[request.address : request.address + request.count])
        return BitsResponse(request.function_code, bits)

    @staticmethod
    def _read_registers(request, table: array) -> RegistersResponse:
        return RegistersResponse(
            request.function_code, tuple(table[request.address : request.address + request.count])
        )

    def _write_single_coil(self, request: WriteSingleCoil) -> WriteSingleCoil:
        self.model.coils[request.address] = request.on
        return request

    def _write_single_register(self, request: WriteSingleRegister) -> WriteSingleRegister:
        self.model.holding_registers[request.address] = request.value
        return request

    def _write_multiple_coils(self, request: WriteMultipleCoils) -> WriteMultipleResponse:
        self.model.coils[request.address : request.address + len(request.values)] = bytes(request.values)
        return WriteMultipleResponse(request.function_code, request.address, len(request.values))

    def _write_multiple_registers(self, request: WriteMultipleRegisters) -> WriteMultipleResponse:
        end = request.address + len(request.values)
        self.model.holding_registers[request.address : end] = array("H", request.values)
        return WriteMultipleResponse(request.function_code, request.address, len(request.values))
