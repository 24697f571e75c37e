"""The PDU layer: what every function code has in common (spec §3).

A PDU is the function code followed by its data.  Each function code is a
pair of small frozen records (codec.record): a ``Request`` that knows its spec limits,
how to encode itself, how long the reply will be and how to check the reply
against itself; and a ``Response`` that encodes and decodes the reply on its
own (the server side and the offline decoder need that).

Lengths are implicit in Modbus: a reader must know from the function code and
the byte-count fields how long a PDU is (spec §2, RTU).  ``Size`` describes
that once per function code.
"""

from __future__ import annotations

import struct
from importlib import import_module
from typing import TYPE_CHECKING, Any, ClassVar

if TYPE_CHECKING:  # for the checker only: a Protocol class costs a one-shot's start-up
    from collections.abc import Callable
    from typing import Protocol, Self

    class Sizer(Protocol):
        """What measures a PDU: ``Size``, or a function's own rule (FC 08, FC 43)."""

        def of(self, pdu: bytes) -> int | None: ...


from mbtool.codec.errors import DecodeError, MismatchError, RequestError, exception_name, function_code_text
from mbtool.codec.record import field, record

MAX_PDU = 253  # RTU: 256 bytes - unit - CRC; MBAP: length field ≤ 254 incl. unit


class ExceptionCode:
    """Exception codes of spec §3 (plain ints: an enum would cost start-up time for nothing)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    ACKNOWLEDGE = 0x05
    SERVER_DEVICE_BUSY = 0x06
    NEGATIVE_ACKNOWLEDGE = 0x07
    MEMORY_PARITY_ERROR = 0x08
    GATEWAY_PATH_UNAVAILABLE = 0x0A
    GATEWAY_TARGET_FAILED_TO_RESPOND = 0x0B


# --- checks shared by the function codes -------------------------------------


def check_u16(value: int, what: str, exception_code: int = ExceptionCode.ILLEGAL_DATA_VALUE) -> None:
    if not 0 <= value <= 0xFFFF:
        raise RequestError(f"{what} {value} is out of range 0..65535", exception_code)


def check_quantity(count: int, limit: int, what: str) -> None:
    if not 1 <= count <= limit:
        raise RequestError(
            f"quantity of {what} {count} is out of range 1..{limit}",
            ExceptionCode.ILLEGAL_DATA_VALUE,
        )


def check_span(address: int, count: int) -> None:
    """Address and address + quantity must stay inside the 65536-item table (spec §1)."""
    check_u16(address, "address", ExceptionCode.ILLEGAL_DATA_ADDRESS)
    if address + count > 0x10000:
        raise RequestError(
            f"address {address} + quantity {count} runs past 65535",
            ExceptionCode.ILLEGAL_DATA_ADDRESS,
        )


def pack_bits(bits: tuple[bool, ...] | list[bool]) -> bytes:
    """Bits LSB first, first bit in bit 0 of the first byte; unused high bits 0 (spec §1)."""
    out = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def unpack_bits(data: bytes, count: int | None = None) -> tuple[bool, ...]:
    n = len(data) * 8 if count is None else count
    return tuple(bool(data[i // 8] >> (i % 8) & 1) for i in range(n))


def pack_registers(registers: tuple[int, ...] | list[int]) -> bytes:
    return struct.pack(f">{len(registers)}H", *registers)


def unpack_registers(data: bytes, start: int = 0) -> tuple[int, ...]:
    """The registers in ``data`` from ``start`` to its end, high byte first."""
    length = len(data) - start
    if length % 2:
        raise DecodeError(f"odd number of register bytes ({length})", data[start:])
    return registers_unpacker(length // 2)(data, start)


def registers_unpacker(count: int) -> Callable[[bytes, int], tuple[int, ...]]:
    """``unpack(data, start)``: ``count`` registers from ``start``, high byte first."""
    unpack = _UNPACK_REGISTERS.get(count)
    if unpack is None:  # one Struct a count, not a format string built and looked up a reply
        unpack = _UNPACK_REGISTERS[count] = struct.Struct(f">{count}H").unpack_from
    return unpack


_UNPACK_REGISTERS: dict = {}


def need(pdu: bytes, length: int, what: str) -> None:
    """A PDU must be exactly as long as its fields say."""
    if len(pdu) != length:
        raise DecodeError(f"{what}: PDU is {len(pdu)} bytes, expected {length}", pdu)


# --- dissection: the fields decode, --hex, --dry-run and the bus monitor show -----
# Each function code's records dissect their own layout with a classmethod
# ``dissect(pdu[, request])``, beside the ``decode`` that reads the same bytes, from
# the pieces here.  A dissection reads what is there: it is shown for a PDU that does
# not decode too, so it never raises on short input (codec.describe cuts it short
# where the bytes end).


@record
class Field:
    name: str  # one token
    raw: bytes  # the bytes on the wire it came from
    value: object
    text: str | None = None  # for people; None: str(value)


def u16(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    value = int.from_bytes(pdu[at : at + 2], "big")
    return Field(
        name, bytes(pdu[at : at + 2]), value, text if text is not None else f"{value} (0x{value:04X})"
    )


def count16(pdu: bytes, at: int, name: str) -> Field:
    """A quantity or a count: shown as a plain number."""
    return u16(pdu, at, name, str(int.from_bytes(pdu[at : at + 2], "big")))


def u8(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    return Field(name, bytes(pdu[at : at + 1]), pdu[at], text if text is not None else str(pdu[at]))


def register_fields(
    pdu: bytes, start: int, end: int, first: int | None, name: str = "register"
) -> list[Field]:
    """Registers from ``start`` to ``end``, labelled by address (``first``) or by index."""
    return [
        u16(pdu, at, f"{name}[{first + i if first is not None else i}]")
        for i, at in enumerate(range(start, end - 1, 2))
    ]


def bit_fields(
    pdu: bytes, start: int, end: int, first: int | None, count: int | None, what: str
) -> list[Field]:
    """Packed bits (spec §1: LSB first), a field a byte, each bit named ON or OFF."""
    out = []
    for i, at in enumerate(range(start, end)):
        byte = pdu[at]
        low = 8 * i
        n = 8 if count is None else max(0, min(8, count - low))
        states = " ".join("ON" if byte >> b & 1 else "OFF" for b in range(n or 8))
        where = (
            f"{what} {first + low}-{first + low + max(n, 1) - 1}"
            if first is not None
            else f"bits {low}-{low + 7}"
        )
        out.append(Field(f"data[{i}]", bytes([byte]), byte, f"0x{byte:02X} {where}: {states}"))
    return out


def busy_status(pdu: bytes, at: int) -> Field:
    """FC 0B / 0C's status word: FFFF busy, 0000 idle (spec §4)."""
    value = int.from_bytes(pdu[at : at + 2], "big")
    meaning = {0xFFFF: "busy", 0x0000: "idle"}.get(value, "neither busy (FFFF) nor idle (0000)")
    return Field("status", bytes(pdu[at : at + 2]), value, f"0x{value:04X} {meaning}")


def printable(data: bytes) -> str:
    return "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in data)


def text_of(value: bytes) -> str:
    """An identification object as text; bytes that are not printable text as hex."""
    try:
        text = value.decode("utf-8")
    except UnicodeDecodeError:
        return value.hex(" ").upper()
    return text if text.isprintable() else value.hex(" ").upper()


# --- sizes --------------------------------------------------------------------


@record
class Size:
    """How long a PDU is: fixed, or given by a byte-count field of ``width`` bytes at ``at``.

    With a count field the PDU is ``at + width + count`` bytes long.
    """

    fixed: int | None = None
    at: int = 0
    width: int = 1

    def of(self, pdu: bytes) -> int | None:
        """Total PDU length, or None while the bytes that tell it have not arrived."""
        if self.fixed is not None:
            return self.fixed
        if len(pdu) < self.at + self.width:
            return None
        return self.at + self.width + int.from_bytes(pdu[self.at : self.at + self.width], "big")


def fixed(n: int) -> Size:
    return Size(fixed=n)


def counted(at: int, width: int = 1) -> Size:
    return Size(at=at, width=width)


# --- the base types -------------------------------------------------------------


@record
class Response:
    """A normal reply.  ``warnings`` holds what a strict reader notices but can live with.

    Every concrete response defines ``encode(self) -> bytes`` (the server side)
    and the classmethod ``decode(cls, pdu) -> Response`` (no ABC: its metaclass
    costs start-up time on every class, and a missing method fails the tests).
    """

    warnings: tuple[str, ...] = field(default=(), kw_only=True, compare=False)

    if TYPE_CHECKING:  # what each concrete response defines (a class value or a field)

        @property
        def function_code(self) -> int: ...

        def encode(self) -> bytes: ...

        @classmethod
        def decode(cls, pdu: bytes) -> Self: ...

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list:
        """The fields after the function code, as Field records (decode, --hex, monitor);
        ``request``, when known, names what the fields are (addresses).  None by default."""
        return []


@record
class ExceptionResponse:
    """The device's 'no': function code | 0x80 and one exception code (spec §3)."""

    function_code: int
    exception_code: int

    @property
    def name(self) -> str:
        return exception_name(self.exception_code)

    def encode(self) -> bytes:
        return bytes([self.function_code | 0x80, self.exception_code])

    @classmethod
    def decode(cls, pdu: bytes) -> ExceptionResponse:
        need(pdu, 2, "exception response")
        return cls(pdu[0] & 0x7F, pdu[1])


@record
class Request:
    """A request PDU.  Subclasses set the class attributes and define ``encode_data(self)``
    (the data after the function code) and the classmethod ``decode(cls, pdu)`` (the
    server side: parse a request PDU, raising DecodeError or RequestError)."""

    function_code: ClassVar[int]
    name: ClassVar[str]
    request_size: ClassVar[Sizer]
    response_size: ClassVar[Sizer]
    response_type: ClassVar[type[Response]]
    broadcastable: ClassVar[bool] = False  # writes may go to unit 0 (spec §2)
    serial_only: ClassVar[bool] = False

    if TYPE_CHECKING:  # what each concrete request defines

        def encode_data(self) -> bytes: ...

        @classmethod
        def decode(cls, pdu: bytes) -> Self: ...

    def encode(self) -> bytes:
        return bytes([self.function_code]) + self.encode_data()

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list:
        """The fields after the function code, as Field records (decode, --hex, --dry-run,
        monitor).  None by default: FC 07, 0B, 0C and 11 requests are the function code alone."""
        return []

    @property
    def expects_response(self) -> bool:
        return True

    def response_length(self, pdu: bytes) -> int | None:
        """Length of the reply to this request; the request may refine the generic rule."""
        return self.response_size.of(pdu)

    @property
    def reply_prefix(self) -> tuple[bytes, int] | None:
        """The reply that answers as asked, as far as it is known before it comes: the first
        bytes of its PDU and the PDU's length.  Reads (FC 01-04) know their function code
        and byte count; other requests None."""
        count = getattr(self, "reply_byte_count", None)
        return None if count is None else (bytes([self.function_code, count]), 2 + count)

    def predicted_decoder(self, at: int) -> Callable[[bytes], Response | ExceptionResponse]:
        """How a reply predicted is decoded, made once a request: ``decode(adu)``, the reply
        whose PDU starts at ``at`` in ``adu``, known to begin as reply_prefix predicted (the
        function and byte count asked for) and to be as long as it said."""
        return lambda adu: self.decode_response(adu[at:])

    def decode_response(self, pdu: bytes) -> Response | ExceptionResponse:
        """Client side: decode a reply PDU and check that it answers this request."""
        if not pdu:
            raise DecodeError("empty response PDU", pdu)
        if pdu[0] == self.function_code | 0x80:
            return ExceptionResponse.decode(pdu)
        if pdu[0] != self.function_code:
            raise MismatchError(
                f"reply has {function_code_text(pdu[0])}, expected {function_code_text(self.function_code)}",
                pdu,
            )
        response = _decode_reply(self.response_type, pdu)
        self.check_response(response)
        return response

    # Any: each request is answered by its own response_type, which its check names.
    def check_response(self, response: Any) -> None:  # noqa: B027 - optional hook, not abstract
        """Does the reply fit the request (byte count vs quantity, echo)?  Raise if not."""

    def _echo_check(self, response: Response) -> None:
        if response != self:
            raise MismatchError(f"reply {response.encode().hex(' ')} does not echo the request", b"")


# The registry: function code -> request type, filled by the function modules as they are
# imported.  Which module registers which code is listed here, so a look-up imports that
# module alone: a one-shot read pays only for the function codes it uses (start-up time is
# what a cron job pays), and a code nobody knows costs no import at all.
FUNCTIONS: dict[int, type[Request]] = {}
FUNCTION_MODULES = {
    "data_access": (0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x16, 0x17, 0x18),
    "serial_line": (0x07, 0x08, 0x0B, 0x0C, 0x11),
    "file_record": (0x14, 0x15),
    "device_id": (0x2B,),
}
_MODULE_OF = {code: module for module, codes in FUNCTION_MODULES.items() for code in codes}


def register(cls: type[Request]) -> type[Request]:
    FUNCTIONS[cls.function_code] = cls
    return cls


def is_known(code: int) -> bool:
    """Does the codec know this function code?  Answered without importing its module."""
    return code in _MODULE_OF


def function_type(code: int) -> type[Request] | None:
    """The request type of a function code, or None if the codec does not know it."""
    kind = FUNCTIONS.get(code)
    if kind is None and code in _MODULE_OF:
        import_module(f"mbtool.codec.{_MODULE_OF[code]}")
        kind = FUNCTIONS[code]
    return kind


def load_all_functions() -> None:
    """Every function module imported now, the whole registry filled (the bus monitor, before
    the first frame comes)."""
    for code in _MODULE_OF:
        function_type(code)


UNKNOWN = -1  # pdu_length() of a function code the codec does not know


def pdu_length(pdu: bytes, response: bool, request: Request | None = None) -> int | None:
    """The full length of the PDU that starts with ``pdu``.

    None: more bytes are needed to tell.  UNKNOWN: the function code is not one
    the codec knows, so only silence (RTU) or a delimiter (ASCII) can end it.
    """
    if not pdu:
        return None
    code = pdu[0]
    if response and code & 0x80:
        return 2
    if request is not None and request.function_code == code:
        return request.response_length(pdu) if response else request.request_size.of(pdu)
    kind = function_type(code)
    if kind is None:
        return UNKNOWN
    return (kind.response_size if response else kind.request_size).of(pdu)


def decode_request(pdu: bytes) -> Request:
    kind = function_type(pdu[0]) if pdu else None
    if kind is None:
        raise DecodeError(f"unknown function code: {function_code_text(pdu[0])}" if pdu else "empty PDU", pdu)
    return kind.decode(pdu)


def check_request(pdu: bytes) -> Request:
    """The request a PDU makes, read as a device reads it: any failure is a RequestError
    carrying the exception code a device answers (spec §3): 01 for a function code the codec
    does not know, 03 for a PDU its function's layout does not fit, else the limit's own."""
    try:
        return decode_request(pdu)
    except DecodeError as error:
        known = bool(pdu) and function_type(pdu[0]) is not None
        code = ExceptionCode.ILLEGAL_DATA_VALUE if known else ExceptionCode.ILLEGAL_FUNCTION
        raise RequestError(str(error), code) from None


def decode_response(pdu: bytes) -> Response | ExceptionResponse:
    """Decode a reply with no request to check it against (offline decoding)."""
    if not pdu:
        raise DecodeError("empty PDU", pdu)
    if pdu[0] & 0x80:
        return ExceptionResponse.decode(pdu)
    kind = function_type(pdu[0])
    if kind is None:
        raise DecodeError(f"unknown function code: {function_code_text(pdu[0])}", pdu)
    return _decode_reply(kind.response_type, pdu)


def _decode_reply(response_type: type[Response], pdu: bytes) -> Response:
    """An echo decodes with its request's checks, but in a reply a bad value is a bad reply, not bad usage."""
    try:
        return response_type.decode(pdu)
    except RequestError as error:
        raise DecodeError(f"invalid reply: {error}", pdu) from error
