"""Serial-line management: FC 07, 08, 11, 12, 17 (spec §3-§6).

These function codes talk about the serial link and the device's view of it
(exception status, diagnostic counters, the communication event log, the
device's identity), so the spec marks them serial only.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import ClassVar

from mbtool.codec.errors import DecodeError, MismatchError, RequestError
from mbtool.codec.pdu import (
    MAX_PDU,
    ExceptionCode,
    Field,
    Request,
    Response,
    busy_status,
    check_u16,
    count16,
    counted,
    fixed,
    need,
    printable,
    register,
    u8,
    u16,
)
from mbtool.codec.record import field, record

MAX_EVENTS = 64  # FC12: the log holds at most 64 event bytes (spec §3)
BUSY = 0xFFFF  # FC11/12 status word: a program command is still being processed
IDLE = 0x0000
RUN_ON = 0xFF  # FC17 run indicator
RUN_OFF = 0x00


def _no_data(pdu: bytes, name: str) -> None:
    need(pdu, 1, name)


class _NoDataRequest(Request):
    """FC 07, 11, 12, 17: the function code alone is the whole request."""

    def encode_data(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, pdu: bytes) -> _NoDataRequest:
        _no_data(pdu, cls.name)
        return cls()


# --- FC 07: Read Exception Status ----------------------------------------------------


@record
class ExceptionStatusResponse(Response):
    """FC 07 reply: one byte, eight device-defined status bits (seed 002: coils 1-8 on a 984)."""

    function_code: ClassVar = 0x07

    status: int

    def encode(self) -> bytes:
        return bytes([self.function_code, self.status])

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        status = pdu[1]
        states = " ".join(f"{b}:{'ON' if status >> b & 1 else 'OFF'}" for b in range(8))
        return [Field("status", bytes(pdu[1:2]), status, f"0x{status:02X} bits {states}")]

    @classmethod
    def decode(cls, pdu: bytes) -> ExceptionStatusResponse:
        need(pdu, 2, "exception status reply")
        return cls(pdu[1])

    @property
    def bits(self) -> tuple[bool, ...]:
        """Bit 0 first, like coils."""
        return tuple(bool(self.status >> i & 1) for i in range(8))


@register
@record
class ReadExceptionStatus(_NoDataRequest):
    function_code: ClassVar = 0x07
    name: ClassVar = "Read Exception Status"
    request_size: ClassVar = fixed(1)
    response_size: ClassVar = fixed(2)
    response_type: ClassVar = ExceptionStatusResponse
    serial_only: ClassVar = True


# --- FC 08: Diagnostics --------------------------------------------------------------


DEFAULT_QUERY_DATA = b"\xa5\x37"  # return-query-data's data when none is given: seed 002's example


class DiagnosticSubFunction(IntEnum):
    """Spec §4.  Seed 002 mislabels BUS_CHAR_OVERRUN_COUNT as 00 11; it is 00 12."""

    RETURN_QUERY_DATA = 0x00
    RESTART_COMMUNICATIONS = 0x01
    RETURN_DIAGNOSTIC_REGISTER = 0x02
    CHANGE_ASCII_DELIMITER = 0x03
    FORCE_LISTEN_ONLY = 0x04
    CLEAR_COUNTERS = 0x0A
    BUS_MESSAGE_COUNT = 0x0B
    BUS_COMM_ERROR_COUNT = 0x0C
    BUS_EXCEPTION_COUNT = 0x0D
    SLAVE_MESSAGE_COUNT = 0x0E
    SLAVE_NO_RESPONSE_COUNT = 0x0F
    SLAVE_NAK_COUNT = 0x10
    SLAVE_BUSY_COUNT = 0x11
    BUS_CHAR_OVERRUN_COUNT = 0x12
    IOP_OVERRUN_COUNT = 0x13
    CLEAR_OVERRUN = 0x14
    MODBUS_PLUS_STATS = 0x15


Sub = DiagnosticSubFunction

# Sub-functions answered by an echo of the request (spec §4).  Restart communications is
# an echo too, but a device leaving listen-only mode does not answer at all.
ECHO_SUB_FUNCTIONS = frozenset(
    {
        Sub.RETURN_QUERY_DATA,
        Sub.RESTART_COMMUNICATIONS,
        Sub.CHANGE_ASCII_DELIMITER,
        Sub.CLEAR_COUNTERS,
        Sub.CLEAR_OVERRUN,
    }
)
RESTART_CLEAR_LOG = b"\xff\x00"  # sub 01 data: also clear the event log
MODBUS_PLUS_GET = b"\x00\x03"  # sub 21 data: get the statistics (0004 clears them)
MODBUS_PLUS_CLEAR = b"\x00\x04"
MODBUS_PLUS_WORDS = 54  # a "get" reply: operation 0003, byte count 0x6C, 54 words


# The names a user types (diag NAME) and reads, one per sub-function of spec §4.
SUB_FUNCTION_NAMES = {
    0x00: "return-query-data",
    0x01: "restart-comms",
    0x02: "diagnostic-register",
    0x03: "change-ascii-delimiter",
    0x04: "force-listen-only",
    0x0A: "clear-counters",
    0x0B: "bus-message-count",
    0x0C: "bus-comm-error-count",
    0x0D: "bus-exception-count",
    0x0E: "slave-message-count",
    0x0F: "slave-no-response-count",
    0x10: "slave-nak-count",
    0x11: "slave-busy-count",
    0x12: "bus-char-overrun-count",
    0x13: "iop-overrun-count",
    0x14: "clear-overrun",
    0x15: "modbus-plus-stats",
}


def sub_function_number(sub: int) -> str:
    """A sub-function number as function codes are written everywhere: hex, two digits (0F)."""
    return f"{sub:02X}"


def sub_function_name(sub: int) -> str:
    """'sub-function 0F slave-no-response-count': the one way messages name a sub-function."""
    name = SUB_FUNCTION_NAMES.get(sub)
    return f"sub-function {sub_function_number(sub)}" + (f" {name}" if name else "")


def _sub(value: int) -> int:
    """A known sub-function as its enum member (for display), any other as a plain int."""
    try:
        return Sub(value)
    except ValueError:
        return value


@record
class _DiagnosticsResponseSize:
    """How long an FC08 reply is when all we have is its first bytes (no request at hand).

    Replies are sub-function + 2 data bytes, except a Modbus Plus "get" (byte count at
    offset 5).  Return-query-data echoes whatever data the request carried, so without
    the request its length cannot be known: 5 is assumed, the common 2-byte query.
    """

    def of(self, pdu: bytes) -> int | None:
        if len(pdu) < 3:
            return None
        if int.from_bytes(pdu[1:3], "big") != Sub.MODBUS_PLUS_STATS:
            return 5
        if len(pdu) < 5:
            return None
        if pdu[3:5] != MODBUS_PLUS_GET:
            return 5
        if len(pdu) < 6:
            return None
        return 6 + pdu[5]


@record
class DiagnosticsResponse(Response):
    """FC 08 reply: sub-function, then data (an echo, a 16-bit register or count, or statistics)."""

    function_code: ClassVar = 0x08

    sub_function: int
    data: bytes = b"\x00\x00"

    def __post_init__(self) -> None:
        object.__setattr__(self, "sub_function", _sub(self.sub_function))
        object.__setattr__(self, "data", bytes(self.data))

    def encode(self) -> bytes:
        return struct.pack(">BH", self.function_code, self.sub_function) + self.data

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return Diagnostics.dissect(pdu)  # the reply has the request's layout

    @classmethod
    def decode(cls, pdu: bytes) -> DiagnosticsResponse:
        if len(pdu) < 3:
            raise DecodeError("diagnostics reply is shorter than its sub-function", pdu)
        sub = _sub(int.from_bytes(pdu[1:3], "big"))
        data = bytes(pdu[3:])
        if sub == Sub.MODBUS_PLUS_STATS and data[:2] == MODBUS_PLUS_GET:
            if len(data) < 3:
                raise DecodeError("Modbus Plus statistics reply has no byte count", pdu)
            need(pdu, 6 + data[2], "Modbus Plus statistics reply")
        return cls(sub, data)

    @property
    def value(self) -> int | None:
        """The 16-bit register or counter of a two-byte reply (subs 02, 0B..13)."""
        return int.from_bytes(self.data, "big") if len(self.data) == 2 else None

    @property
    def statistics(self) -> tuple[int, ...] | None:
        """The words of a Modbus Plus "get" reply (operation, byte count, words)."""
        if (
            self.sub_function != Sub.MODBUS_PLUS_STATS
            or self.data[:2] != MODBUS_PLUS_GET
            or len(self.data) < 3
        ):
            return None
        words = self.data[3 : 3 + self.data[2]]
        return struct.unpack(f">{len(words) // 2}H", words[: len(words) // 2 * 2])


@register
@record
class Diagnostics(Request):
    """FC 08 (spec §4).

    The reply's length depends on the request: a return-query-data echo is as long
    as the query.  ``response_length`` knows that; the class-level ``response_size``
    (used when decoding a capture with no request) assumes a 2-byte query, and a
    device reading requests (``request_size``) likewise assumes 2 data bytes, so
    a longer return-query-data request is only framed correctly over TCP.
    """

    function_code: ClassVar = 0x08
    name: ClassVar = "Diagnostics"
    request_size: ClassVar = fixed(5)
    response_size: ClassVar = _DiagnosticsResponseSize()
    response_type: ClassVar = DiagnosticsResponse
    serial_only: ClassVar = True

    sub_function: int
    data: bytes = b"\x00\x00"

    def __post_init__(self) -> None:
        check_u16(self.sub_function, "diagnostics sub-function")
        object.__setattr__(self, "sub_function", _sub(self.sub_function))
        object.__setattr__(self, "data", bytes(self.data))
        if len(self.data) > MAX_PDU - 3:
            raise RequestError(
                f"diagnostics data of {len(self.data)} bytes exceeds {MAX_PDU - 3}",
                ExceptionCode.ILLEGAL_DATA_VALUE,
            )
        if (
            isinstance(self.sub_function, Sub)
            and self.sub_function != Sub.RETURN_QUERY_DATA
            and len(self.data) != 2
        ):
            raise RequestError(
                f"{sub_function_name(self.sub_function)} takes 2 data bytes, not {len(self.data)}",
                ExceptionCode.ILLEGAL_DATA_VALUE,
            )

    def encode_data(self) -> bytes:
        return struct.pack(">H", self.sub_function) + self.data

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        sub = int.from_bytes(pdu[1:3], "big")
        name = SUB_FUNCTION_NAMES.get(sub, "not in the spec")
        fields = [u16(pdu, 1, "sub_function", f"{sub_function_number(sub)} {name}")]
        if len(pdu) > 3:
            data = bytes(pdu[3:])
            text = data.hex(" ").upper()
            if len(data) == 2:
                text += f" ({int.from_bytes(data, 'big')})"
            fields.append(Field("data", data, int.from_bytes(data, "big") if len(data) <= 8 else text, text))
        return fields

    @classmethod
    def decode(cls, pdu: bytes) -> Diagnostics:
        if len(pdu) < 3:
            raise DecodeError(f"{cls.name}: request is shorter than its sub-function", pdu)
        return cls(int.from_bytes(pdu[1:3], "big"), bytes(pdu[3:]))

    @property
    def expects_response(self) -> bool:
        return self.sub_function != Sub.FORCE_LISTEN_ONLY

    def response_length(self, pdu: bytes) -> int | None:
        if self.sub_function == Sub.RETURN_QUERY_DATA:
            return 3 + len(self.data)
        if self.sub_function == Sub.MODBUS_PLUS_STATS and self.data == MODBUS_PLUS_GET:
            return self.response_size.of(pdu)
        return 5

    def check_response(self, response: DiagnosticsResponse) -> None:
        if response.sub_function != self.sub_function:
            raise MismatchError(
                f"reply is for {sub_function_name(response.sub_function)},"
                f" expected {sub_function_name(self.sub_function)}"
            )
        echo = self.sub_function in ECHO_SUB_FUNCTIONS or (
            self.sub_function == Sub.MODBUS_PLUS_STATS and self.data != MODBUS_PLUS_GET
        )
        if echo and response.data != self.data:
            raise MismatchError(
                f"{sub_function_name(self.sub_function)} reply data {response.data.hex(' ').upper()}"
                f" does not echo {self.data.hex(' ').upper()}"
            )
        if self.sub_function == Sub.MODBUS_PLUS_STATS and self.data == MODBUS_PLUS_GET:
            if response.data[:2] != MODBUS_PLUS_GET:
                raise MismatchError("Modbus Plus reply does not carry the get operation 0003")
        elif (
            isinstance(self.sub_function, Sub)
            and not echo
            and self.expects_response  # a reply to force-listen-only has no layout to hold it to
            and len(response.data) != 2
        ):
            raise MismatchError(
                f"{sub_function_name(self.sub_function)} reply carries {len(response.data)} data bytes, expected 2"
            )


# --- FC 11: Get Comm Event Counter ---------------------------------------------------


def _status_warnings(status: int) -> tuple[str, ...]:
    if status in (BUSY, IDLE):
        return ()
    return (f"status word {status:04X} is neither 0000 (idle) nor FFFF (busy)",)


@record
class CommEventCounterResponse(Response):
    """FC 11 reply: status word (FFFF busy, 0000 idle) and the event counter."""

    function_code: ClassVar = 0x0B

    status: int
    event_count: int

    @property
    def busy(self) -> bool:
        return self.status == BUSY

    def encode(self) -> bytes:
        return struct.pack(">BHH", self.function_code, self.status, self.event_count)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        return [busy_status(pdu, 1), count16(pdu, 3, "event_count")]

    @classmethod
    def decode(cls, pdu: bytes) -> CommEventCounterResponse:
        need(pdu, 5, "comm event counter reply")
        status, count = struct.unpack_from(">HH", pdu, 1)
        return cls(status, count, warnings=_status_warnings(status))


@register
@record
class GetCommEventCounter(_NoDataRequest):
    function_code: ClassVar = 0x0B
    name: ClassVar = "Get Comm Event Counter"
    request_size: ClassVar = fixed(1)
    response_size: ClassVar = fixed(5)
    response_type: ClassVar = CommEventCounterResponse
    serial_only: ClassVar = True


# --- FC 12: Get Comm Event Log -------------------------------------------------------

_RECEIVE_BITS = {
    1: "communication error",
    4: "character overrun",
    5: "currently in listen-only mode",
    6: "broadcast received",
}
_SEND_BITS = {
    0: "read exception sent (codes 1-3)",
    1: "slave abort exception sent (code 4)",
    2: "slave busy exception sent (codes 5-6)",
    3: "slave program NAK exception sent (code 7)",
    4: "write timeout error occurred",
    5: "currently in listen-only mode",
}


def describe_event(byte: int) -> str:
    """One event byte of the FC12 log in words (spec §5).

    0x20 is neither a send nor a receive event, whatever seed 002 says: it is
    reported as unrecognised rather than guessed at.
    """
    if not 0 <= byte <= 0xFF:
        raise RequestError(f"event byte {byte} is out of range 0..255")
    if byte & 0x80:
        kind, bits, mask = "receive event", _RECEIVE_BITS, 0x7F
    elif byte & 0x40:
        kind, bits, mask = "send event", _SEND_BITS, 0x3F
    elif byte == 0x04:
        return "entered listen-only mode"
    elif byte == 0x00:
        return "communications restart"
    else:
        return f"unrecognised event 0x{byte:02X}"
    parts = [text for bit, text in bits.items() if byte & mask & (1 << bit)]
    return f"{kind}: {', '.join(parts)}" if parts else kind


@record
class CommEventLogResponse(Response):
    """FC 12 reply: byte count (6 + events), status, event count, message count, events.

    Event 0 is the newest.
    """

    function_code: ClassVar = 0x0C

    status: int
    event_count: int
    message_count: int
    events: bytes = b""

    @property
    def busy(self) -> bool:
        return self.status == BUSY

    @property
    def descriptions(self) -> tuple[str, ...]:
        return tuple(describe_event(event) for event in self.events)

    def encode(self) -> bytes:
        head = struct.pack(
            ">BBHHH",
            self.function_code,
            6 + len(self.events),
            self.status,
            self.event_count,
            self.message_count,
        )
        return head + self.events

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        fields = [
            u8(pdu, 1, "byte_count"),
            busy_status(pdu, 2),
            count16(pdu, 4, "event_count"),
            count16(pdu, 6, "message_count"),
        ]
        for i, byte in enumerate(pdu[8:]):
            fields.append(Field(f"event[{i}]", bytes([byte]), byte, f"0x{byte:02X} {describe_event(byte)}"))
        return fields

    @classmethod
    def decode(cls, pdu: bytes) -> CommEventLogResponse:
        if len(pdu) < 2:
            raise DecodeError("comm event log reply is shorter than its byte count field", pdu)
        need(pdu, 2 + pdu[1], "comm event log reply")
        if pdu[1] < 6:
            raise DecodeError(f"comm event log byte count {pdu[1]} is below 6", pdu)
        events = bytes(pdu[8:])
        if len(events) > MAX_EVENTS:
            raise DecodeError(f"comm event log carries {len(events)} events, at most {MAX_EVENTS}", pdu)
        status, event_count, message_count = struct.unpack_from(">HHH", pdu, 2)
        return cls(status, event_count, message_count, events, warnings=_status_warnings(status))


@register
@record
class GetCommEventLog(_NoDataRequest):
    function_code: ClassVar = 0x0C
    name: ClassVar = "Get Comm Event Log"
    request_size: ClassVar = fixed(1)
    response_size: ClassVar = counted(1)
    response_type: ClassVar = CommEventLogResponse
    serial_only: ClassVar = True


# --- FC 17: Report Slave ID ----------------------------------------------------------

MODICON_SLAVE_IDS = {0: "Micro 84", 1: "484", 2: "184/384", 3: "584", 8: "884", 9: "984"}  # spec §6


@record
class ReportSlaveIdResponse(Response):
    """FC 17 reply: byte count, slave id, run indicator (00 off / FF on), device-specific bytes.

    A run indicator byte that is neither 00 nor FF is kept in ``run_indicator_byte``
    (and read as on if non-zero) with a warning; it is None for the two proper values.
    """

    function_code: ClassVar = 0x11

    slave_id: int
    run_indicator: bool
    extra: bytes = b""
    run_indicator_byte: int | None = field(default=None, kw_only=True)

    def encode(self) -> bytes:
        run = self.run_indicator_byte
        if run is None:
            run = RUN_ON if self.run_indicator else RUN_OFF
        return bytes([self.function_code, 2 + len(self.extra), self.slave_id, run]) + self.extra

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        from mbtool.codec.modicon import (  # noqa: PLC0415 - FC17's dissection only; sim:// loads this module
            MODICON_BYTES,
            SLAVE_IDS,
            modicon_fields,
            modicon_layout,
        )

        slave_id, run = pdu[2], pdu[3]
        extra = bytes(pdu[4:])
        layout = modicon_layout(slave_id, extra)
        id_text = str(slave_id) + (f" (Modicon {SLAVE_IDS[slave_id]})" if layout else "")
        run_text = {0xFF: "ON", 0x00: "OFF"}.get(run, f"0x{run:02X}: neither 00 (OFF) nor FF (ON)")
        fields = [
            u8(pdu, 1, "byte_count"),
            u8(pdu, 2, "slave_id", id_text),
            u8(pdu, 3, "run_indicator", run_text),
        ]
        if layout:
            for name, value, text in modicon_fields(layout, extra):
                at, size = MODICON_BYTES.get(name) or (2 + 2 * int(name.removeprefix("pib_")), 2)
                fields.append(Field(name, extra[at : at + size], value, text))
        elif extra:
            shown = extra.hex(" ").upper()
            fields.append(Field("extra", extra, shown, f'{shown} "{printable(extra)}"'))
        return fields

    @classmethod
    def decode(cls, pdu: bytes) -> ReportSlaveIdResponse:
        if len(pdu) < 2:
            raise DecodeError("report slave id reply is shorter than its byte count field", pdu)
        need(pdu, 2 + pdu[1], "report slave id reply")
        if pdu[1] < 2:
            raise DecodeError(
                f"report slave id byte count {pdu[1]} is below 2 (slave id, run indicator)", pdu
            )
        slave_id, run = pdu[2], pdu[3]
        if run in (RUN_ON, RUN_OFF):
            return cls(slave_id, run == RUN_ON, bytes(pdu[4:]))
        warning = f"run indicator byte {run:02X} is neither 00 (off) nor FF (on)"
        if pdu[-1] in (RUN_ON, RUN_OFF) and len(pdu) > 4:
            # pymodbus 3.16 sends its identity text first and the run indicator last
            warning += f"; the last byte is {pdu[-1]:02X}: the device may send the run indicator last"
        return cls(slave_id, run != RUN_OFF, bytes(pdu[4:]), run_indicator_byte=run, warnings=(warning,))


@register
@record
class ReportSlaveId(_NoDataRequest):
    function_code: ClassVar = 0x11
    name: ClassVar = "Report Slave ID"
    request_size: ClassVar = fixed(1)
    response_size: ClassVar = counted(1)
    response_type: ClassVar = ReportSlaveIdResponse
    serial_only: ClassVar = True
