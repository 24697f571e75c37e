"""Bit and register access: FC 01, 02, 03, 04, 05, 06, 15, 16, 22, 23, 24 (spec §3).

Limits are those of the current spec: 2000 bits and 125 registers read,
1968 coils and 123 registers written (seed 000's 0x78 for FC16 is wrong),
121 registers written by FC23, 31 entries in a FIFO queue (FC24).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, ClassVar

from mbtool.codec.errors import DecodeError, MismatchError, RequestError
from mbtool.codec.pdu import (
    ExceptionCode,
    ExceptionResponse,
    Field,
    Request,
    Response,
    bit_fields,
    check_quantity,
    check_span,
    check_u16,
    count16,
    counted,
    fixed,
    need,
    pack_bits,
    pack_registers,
    register,
    register_fields,
    registers_unpacker,
    u8,
    u16,
    unpack_bits,
    unpack_registers,
)
from mbtool.codec.record import record

MAX_READ_BITS = 2000
MAX_READ_REGISTERS = 125
MAX_WRITE_COILS = 1968  # 0x7B0
MAX_WRITE_REGISTERS = 123  # 0x7B
MAX_READ_WRITE_REGISTERS = 121  # FC23's write part: 0x79
MAX_FIFO_COUNT = 31

COIL_ON = 0xFF00
COIL_OFF = 0x0000


def _address_and_count(pdu: bytes, name: str) -> tuple[int, int]:
    need(pdu, 5, name)
    return struct.unpack_from(">HH", pdu, 1)


def _address_and_count_fields(pdu: bytes) -> list[Field]:
    """The fields _address_and_count reads: FC 01-04 requests, FC 0F/10 requests and replies."""
    return [u16(pdu, 1, "starting_address"), count16(pdu, 3, "quantity")]


def mask_formula(and_mask: int, or_mask: int) -> str:
    """FC22 in words: (current AND and) OR (or AND NOT and), spec §3 (not seed 002's formula)."""
    forced_on = or_mask & ~and_mask & 0xFFFF
    forced_off = ~and_mask & ~or_mask & 0xFFFF
    return (
        f"(current AND 0x{and_mask:04X}) OR (0x{or_mask:04X} AND NOT 0x{and_mask:04X})"
        f" = (current AND 0x{and_mask:04X}) OR 0x{forced_on:04X}: keeps bits 0x{and_mask:04X},"
        f" sets 0x{forced_on:04X}, clears 0x{forced_off:04X}"
    )


# --- reads: FC 01 / 02 (bits) and 03 / 04 (registers) ----------------------------


@record
class BitsResponse(Response):
    """FC 01 / 02 reply: byte count, then bits packed LSB first."""

    function_code: int
    bits: tuple[bool, ...]  # every bit of the data bytes; the request trims to its count

    def __init__(self, function_code: int, bits: tuple[bool, ...], *, warnings: tuple[str, ...] = ()) -> None:
        # By hand: one a transaction in a polling loop (codec/record.py).
        fields = self.__dict__
        fields["function_code"] = function_code
        fields["bits"] = bits
        fields["warnings"] = warnings

    def encode(self) -> bytes:
        data = pack_bits(self.bits)
        return bytes([self.function_code, len(data)]) + data

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        count, first = getattr(request, "count", None), getattr(request, "address", None)
        what = "coils" if pdu[0] == 0x01 else "inputs"
        return [u8(pdu, 1, "byte_count")] + bit_fields(pdu, 2, len(pdu), first, count, what)

    @classmethod
    def decode(cls, pdu: bytes) -> BitsResponse:
        if len(pdu) < 2:
            raise DecodeError("bits reply is shorter than its byte count field", pdu)
        need(pdu, 2 + pdu[1], "bits reply")
        return cls(pdu[0], unpack_bits(pdu[2:]))


@record
class RegistersResponse(Response):
    """FC 03 / 04 / 23 reply: byte count, then registers high byte first."""

    function_code: int
    registers: tuple[int, ...]

    def __init__(
        self, function_code: int, registers: tuple[int, ...], *, warnings: tuple[str, ...] = ()
    ) -> None:
        # By hand: one a transaction in a polling loop (codec/record.py).
        fields = self.__dict__
        fields["function_code"] = function_code
        fields["registers"] = registers
        fields["warnings"] = warnings

    def encode(self) -> bytes:
        return bytes([self.function_code, 2 * len(self.registers)]) + pack_registers(self.registers)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        first = getattr(request, "address", getattr(request, "read_address", None))
        return [u8(pdu, 1, "byte_count")] + register_fields(pdu, 2, len(pdu), first)

    @classmethod
    def decode(cls, pdu: bytes) -> RegistersResponse:
        if len(pdu) < 2:
            raise DecodeError("registers reply is shorter than its byte count field", pdu)
        need(pdu, 2 + pdu[1], "registers reply")
        return cls(pdu[0], unpack_registers(pdu, 2))


@record
class _ReadBits(Request):
    address: int
    count: int = 1

    request_size: ClassVar = fixed(5)
    response_size: ClassVar = counted(1)
    response_type: ClassVar = BitsResponse

    def __post_init__(self) -> None:
        check_quantity(self.count, MAX_READ_BITS, self.name.lower().removeprefix("read "))
        check_span(self.address, self.count)

    def encode_data(self) -> bytes:
        return struct.pack(">HH", self.address, self.count)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return _address_and_count_fields(pdu)

    @classmethod
    def decode(cls, pdu: bytes) -> _ReadBits:
        return cls(*_address_and_count(pdu, cls.name))

    def decode_response(self, pdu: bytes):
        response = super().decode_response(pdu)
        if isinstance(response, BitsResponse):
            # The reply carries whole bytes; only the first `count` bits were asked for.
            padding = response.bits[self.count :]
            warnings = ("unused high bits of the last byte are not zero",) if any(padding) else ()
            response = BitsResponse(response.function_code, response.bits[: self.count], warnings=warnings)
        return response

    @property
    def reply_byte_count(self) -> int:
        """The byte count the reply must carry: the bits asked for, in whole bytes."""
        return (self.count + 7) // 8

    def check_response(self, response: BitsResponse) -> None:
        expected = self.reply_byte_count
        if len(response.bits) != 8 * expected:
            raise MismatchError(
                f"byte count {len(response.bits) // 8} does not fit {self.count} bits (expected {expected})"
            )


@register
@record
class ReadCoils(_ReadBits):
    function_code: ClassVar = 0x01
    name: ClassVar = "Read Coils"


@register
@record
class ReadDiscreteInputs(_ReadBits):
    function_code: ClassVar = 0x02
    name: ClassVar = "Read Discrete Inputs"


def _check_register_count(response: RegistersResponse, count: int) -> None:
    """The byte count must fit the quantity asked for (libmodbus CVE-2019-14462/3 were this check)."""
    if len(response.registers) != count:
        raise MismatchError(
            f"byte count {2 * len(response.registers)} does not fit {count} registers (expected {2 * count})"
        )


@record
class _ReadRegisters(Request):
    address: int
    count: int = 1

    request_size: ClassVar = fixed(5)
    response_size: ClassVar = counted(1)

    @property
    def reply_byte_count(self) -> int:
        """The byte count the reply must carry: two bytes a register asked for."""
        return 2 * self.count

    response_type: ClassVar = RegistersResponse

    def __post_init__(self) -> None:
        check_quantity(self.count, MAX_READ_REGISTERS, "registers")
        check_span(self.address, self.count)

    def encode_data(self) -> bytes:
        return struct.pack(">HH", self.address, self.count)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return _address_and_count_fields(pdu)

    @classmethod
    def decode(cls, pdu: bytes) -> _ReadRegisters:
        return cls(*_address_and_count(pdu, cls.name))

    def predicted_decoder(self, at: int) -> Callable[[bytes], Response | ExceptionResponse]:
        # Its function code and byte count are as asked: the registers follow them.
        code, unpack, start = self.function_code, registers_unpacker(self.count), at + 2
        return lambda adu: RegistersResponse(code, unpack(adu, start))

    def decode_response(self, pdu: bytes) -> Response | ExceptionResponse:
        # The reply as asked for, which a poll nearly always gets, is taken at once: the
        # function code, the byte count for the registers asked for and that many bytes.
        # Anything else goes through Request's checks, which say what is wrong with it.
        byte_count = 2 * self.count
        if len(pdu) == 2 + byte_count and pdu[1] == byte_count and pdu[0] == self.function_code:
            return RegistersResponse(pdu[0], unpack_registers(pdu, 2))
        return super().decode_response(pdu)

    def check_response(self, response: RegistersResponse) -> None:
        _check_register_count(response, self.count)


@register
@record
class ReadHoldingRegisters(_ReadRegisters):
    function_code: ClassVar = 0x03
    name: ClassVar = "Read Holding Registers"


@register
@record
class ReadInputRegisters(_ReadRegisters):
    function_code: ClassVar = 0x04
    name: ClassVar = "Read Input Registers"


# --- single writes: FC 05 / 06, answered by an echo --------------------------------


@register
@record
class WriteSingleCoil(Request, Response):
    """FC 05: value FF00 = ON, 0000 = OFF; anything else is exception 03."""

    function_code: ClassVar = 0x05
    name: ClassVar = "Write Single Coil"
    request_size: ClassVar = fixed(5)
    response_size: ClassVar = fixed(5)
    broadcastable: ClassVar = True

    address: int
    on: bool

    def __post_init__(self) -> None:
        check_u16(self.address, "address", ExceptionCode.ILLEGAL_DATA_ADDRESS)

    def encode_data(self) -> bytes:
        return struct.pack(">HH", self.address, COIL_ON if self.on else COIL_OFF)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        value = int.from_bytes(pdu[3:5], "big")
        state = {COIL_ON: "ON", COIL_OFF: "OFF"}.get(value, "invalid: neither FF00 nor 0000")
        return [u16(pdu, 1, "output_address"), u16(pdu, 3, "output_value", f"0x{value:04X} {state}")]

    @classmethod
    def decode(cls, pdu: bytes) -> WriteSingleCoil:
        address, value = _address_and_count(pdu, cls.name)
        if value not in (COIL_ON, COIL_OFF):
            raise RequestError(
                f"coil value {value:04X} is neither FF00 nor 0000", ExceptionCode.ILLEGAL_DATA_VALUE
            )
        return cls(address, value == COIL_ON)

    def check_response(self, response: Response) -> None:
        self._echo_check(response)


WriteSingleCoil.response_type = WriteSingleCoil  # the reply is an echo of the request


@register
@record
class WriteSingleRegister(Request, Response):
    function_code: ClassVar = 0x06
    name: ClassVar = "Write Single Register"
    request_size: ClassVar = fixed(5)
    response_size: ClassVar = fixed(5)
    broadcastable: ClassVar = True

    address: int
    value: int

    def __post_init__(self) -> None:
        check_u16(self.address, "address", ExceptionCode.ILLEGAL_DATA_ADDRESS)
        check_u16(self.value, "register value")

    def encode_data(self) -> bytes:
        return struct.pack(">HH", self.address, self.value)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return [u16(pdu, 1, "register_address"), u16(pdu, 3, "register_value")]

    @classmethod
    def decode(cls, pdu: bytes) -> WriteSingleRegister:
        return cls(*_address_and_count(pdu, cls.name))

    def check_response(self, response: Response) -> None:
        self._echo_check(response)


WriteSingleRegister.response_type = WriteSingleRegister


# --- multiple writes: FC 15 / 16 --------------------------------------------------


@record
class WriteMultipleResponse(Response):
    """FC 15 / 16 reply: starting address and quantity written."""

    function_code: int
    address: int
    count: int

    def encode(self) -> bytes:
        return struct.pack(">BHH", self.function_code, self.address, self.count)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return _address_and_count_fields(pdu)

    @classmethod
    def decode(cls, pdu: bytes) -> WriteMultipleResponse:
        address, count = _address_and_count(pdu, "write multiple reply")
        return cls(pdu[0], address, count)


@record
class _WriteMultiple(Request):
    request_size: ClassVar = counted(5)
    response_size: ClassVar = fixed(5)
    response_type: ClassVar = WriteMultipleResponse
    broadcastable: ClassVar = True

    if TYPE_CHECKING:  # the fields each write defines (coils: bits; registers: words)

        @property
        def address(self) -> int: ...

        @property
        def values(self) -> Sequence[int]: ...

    def check_response(self, response: WriteMultipleResponse) -> None:
        count = len(self.values)
        if (response.address, response.count) != (self.address, count):
            raise MismatchError(
                f"reply confirms {response.count} at {response.address}, expected {count} at {self.address}"
            )

    @classmethod
    def _split(cls, pdu: bytes) -> tuple[int, int, bytes]:
        if len(pdu) < 6:
            raise DecodeError(f"{cls.name}: request is shorter than its byte count field", pdu)
        need(pdu, 6 + pdu[5], cls.name)
        address, count = struct.unpack_from(">HH", pdu, 1)
        return address, count, pdu[6:]


@register
@record
class WriteMultipleCoils(_WriteMultiple):
    function_code: ClassVar = 0x0F
    name: ClassVar = "Write Multiple Coils"

    address: int
    values: tuple[bool, ...]

    def __post_init__(self) -> None:
        check_quantity(len(self.values), MAX_WRITE_COILS, "coils")
        check_span(self.address, len(self.values))

    def encode_data(self) -> bytes:
        data = pack_bits(self.values)
        return struct.pack(">HHB", self.address, len(self.values), len(data)) + data

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        count, address = int.from_bytes(pdu[3:5], "big"), int.from_bytes(pdu[1:3], "big")
        head = _address_and_count_fields(pdu) + [u8(pdu, 5, "byte_count")]
        return head + bit_fields(pdu, 6, len(pdu), address, count, "coils")

    @classmethod
    def decode(cls, pdu: bytes) -> WriteMultipleCoils:
        address, count, data = cls._split(pdu)
        check_quantity(count, MAX_WRITE_COILS, "coils")
        if len(data) != (count + 7) // 8:
            raise RequestError(f"byte count {len(data)} does not fit {count} coils")
        return cls(address, unpack_bits(data, count))


@register
@record
class WriteMultipleRegisters(_WriteMultiple):
    function_code: ClassVar = 0x10
    name: ClassVar = "Write Multiple Registers"

    address: int
    values: tuple[int, ...]

    def __post_init__(self) -> None:
        check_quantity(len(self.values), MAX_WRITE_REGISTERS, "registers")
        check_span(self.address, len(self.values))
        for value in self.values:
            check_u16(value, "register value")

    def encode_data(self) -> bytes:
        n = len(self.values)
        return struct.pack(">HHB", self.address, n, 2 * n) + pack_registers(self.values)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        address = int.from_bytes(pdu[1:3], "big")
        head = _address_and_count_fields(pdu) + [u8(pdu, 5, "byte_count")]
        return head + register_fields(pdu, 6, len(pdu), address)

    @classmethod
    def decode(cls, pdu: bytes) -> WriteMultipleRegisters:
        address, count, data = cls._split(pdu)
        check_quantity(count, MAX_WRITE_REGISTERS, "registers")
        if len(data) != 2 * count:
            raise RequestError(f"byte count {len(data)} does not fit {count} registers")
        return cls(address, unpack_registers(data))


# --- FC 22: mask write, answered by an echo ----------------------------------------


def mask_write_result(current: int, and_mask: int, or_mask: int) -> int:
    """What FC22 leaves in the register: (current AND and_mask) OR (or_mask AND NOT and_mask).

    Spec §3: seed 002 prints ``or_mask AND and_mask``; its own example (0x12, F2, 25 -> 17)
    only holds with the complement.
    """
    return ((current & and_mask) | (or_mask & ~and_mask)) & 0xFFFF


@register
@record
class MaskWriteRegister(Request, Response):
    function_code: ClassVar = 0x16
    name: ClassVar = "Mask Write Register"
    request_size: ClassVar = fixed(7)
    response_size: ClassVar = fixed(7)
    broadcastable: ClassVar = True

    address: int
    and_mask: int
    or_mask: int

    def __post_init__(self) -> None:
        check_u16(self.address, "address", ExceptionCode.ILLEGAL_DATA_ADDRESS)
        check_u16(self.and_mask, "AND mask")
        check_u16(self.or_mask, "OR mask")

    def encode_data(self) -> bytes:
        return struct.pack(">HHH", self.address, self.and_mask, self.or_mask)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        and_mask, or_mask = int.from_bytes(pdu[3:5], "big"), int.from_bytes(pdu[5:7], "big")
        formula = mask_formula(and_mask, or_mask)
        return [
            u16(pdu, 1, "reference_address"),
            u16(pdu, 3, "and_mask", f"0x{and_mask:04X}"),
            u16(pdu, 5, "or_mask", f"0x{or_mask:04X}"),
            Field("result", b"", formula, formula),
        ]

    @classmethod
    def decode(cls, pdu: bytes) -> MaskWriteRegister:
        need(pdu, 7, cls.name)
        return cls(*struct.unpack_from(">HHH", pdu, 1))

    def result(self, current: int) -> int:
        """The register's new value, given its current one."""
        return mask_write_result(current, self.and_mask, self.or_mask)

    def check_response(self, response: Response) -> None:
        self._echo_check(response)


MaskWriteRegister.response_type = MaskWriteRegister


# --- FC 23: write, then read, in one transaction ----------------------------------


@register
@record
class ReadWriteMultipleRegisters(Request):
    """FC 23: the write is done before the read (spec §3); the reply is FC03's layout."""

    function_code: ClassVar = 0x17
    name: ClassVar = "Read/Write Multiple Registers"
    request_size: ClassVar = counted(9)
    response_size: ClassVar = counted(1)
    response_type: ClassVar = RegistersResponse

    read_address: int
    read_count: int
    write_address: int
    values: tuple[int, ...]

    def __post_init__(self) -> None:
        check_quantity(self.read_count, MAX_READ_REGISTERS, "registers to read")
        check_span(self.read_address, self.read_count)
        check_quantity(len(self.values), MAX_READ_WRITE_REGISTERS, "registers to write")
        check_span(self.write_address, len(self.values))
        for value in self.values:
            check_u16(value, "register value")

    def encode_data(self) -> bytes:
        n = len(self.values)
        head = struct.pack(">HHHHB", self.read_address, self.read_count, self.write_address, n, 2 * n)
        return head + pack_registers(self.values)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        write_address = int.from_bytes(pdu[5:7], "big")
        return [
            u16(pdu, 1, "read_starting_address"),
            count16(pdu, 3, "quantity_to_read"),
            u16(pdu, 5, "write_starting_address"),
            count16(pdu, 7, "quantity_to_write"),
            u8(pdu, 9, "write_byte_count"),
        ] + register_fields(pdu, 10, len(pdu), write_address)

    @classmethod
    def decode(cls, pdu: bytes) -> ReadWriteMultipleRegisters:
        if len(pdu) < 10:
            raise DecodeError(f"{cls.name}: request is shorter than its byte count field", pdu)
        need(pdu, 10 + pdu[9], cls.name)
        read_address, read_count, write_address, write_count = struct.unpack_from(">HHHH", pdu, 1)
        check_quantity(read_count, MAX_READ_REGISTERS, "registers to read")
        check_quantity(write_count, MAX_READ_WRITE_REGISTERS, "registers to write")
        if pdu[9] != 2 * write_count:
            raise RequestError(f"byte count {pdu[9]} does not fit {write_count} registers")
        return cls(read_address, read_count, write_address, unpack_registers(pdu[10:]))

    def check_response(self, response: RegistersResponse) -> None:
        _check_register_count(response, self.read_count)


# --- FC 24: read a FIFO queue ------------------------------------------------------


@record
class ReadFifoQueueResponse(Response):
    """FC 24 reply: byte count (2 bytes) = 2 + 2 × FIFO count, FIFO count (2 bytes), registers."""

    function_code: ClassVar = 0x18

    registers: tuple[int, ...]

    def __post_init__(self) -> None:
        # A server with more than 31 entries answers exception 03 instead (spec §3).
        if len(self.registers) > MAX_FIFO_COUNT:
            raise RequestError(
                f"FIFO count {len(self.registers)} exceeds {MAX_FIFO_COUNT}",
                ExceptionCode.ILLEGAL_DATA_VALUE,
            )

    def encode(self) -> bytes:
        n = len(self.registers)
        return struct.pack(">BHH", self.function_code, 2 + 2 * n, n) + pack_registers(self.registers)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        head = [count16(pdu, 1, "byte_count"), count16(pdu, 3, "fifo_count")]
        return head + register_fields(pdu, 5, len(pdu), None, "fifo")

    @classmethod
    def decode(cls, pdu: bytes) -> ReadFifoQueueResponse:
        if len(pdu) < 5:
            raise DecodeError("FIFO reply is shorter than its byte count and FIFO count fields", pdu)
        byte_count, fifo_count = struct.unpack_from(">HH", pdu, 1)
        need(pdu, 3 + byte_count, "FIFO reply")
        if byte_count != 2 + 2 * fifo_count:
            raise DecodeError(f"byte count {byte_count} does not fit FIFO count {fifo_count}", pdu)
        if fifo_count > MAX_FIFO_COUNT:
            raise DecodeError(f"FIFO count {fifo_count} exceeds {MAX_FIFO_COUNT}", pdu)
        return cls(unpack_registers(pdu[5:]))


@register
@record
class ReadFifoQueue(Request):
    function_code: ClassVar = 0x18
    name: ClassVar = "Read FIFO Queue"
    request_size: ClassVar = fixed(3)
    response_size: ClassVar = counted(1, width=2)
    response_type: ClassVar = ReadFifoQueueResponse

    address: int  # the FIFO pointer register

    def __post_init__(self) -> None:
        check_u16(self.address, "FIFO pointer address", ExceptionCode.ILLEGAL_DATA_ADDRESS)

    def encode_data(self) -> bytes:
        return struct.pack(">H", self.address)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return [u16(pdu, 1, "fifo_pointer_address")]

    @classmethod
    def decode(cls, pdu: bytes) -> ReadFifoQueue:
        need(pdu, 3, cls.name)
        return cls(*struct.unpack_from(">H", pdu, 1))
