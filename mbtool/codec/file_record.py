"""Extended memory, file records: FC 20 and 21 (spec §1, §3).

A file is up to 10000 registers (records 0..9999) numbered 1..65535; each
request carries several groups ("sub-requests"), each of reference type 6.
The byte count bounds the number of groups: 0x07..0xF5 for a read request,
0x09..0xFB for a write.
"""

from __future__ import annotations

import struct
from typing import ClassVar

from mbtool.codec.errors import DecodeError, MismatchError, RequestError
from mbtool.codec.pdu import (
    ExceptionCode,
    Field,
    Request,
    Response,
    check_u16,
    count16,
    counted,
    need,
    pack_registers,
    register,
    register_fields,
    u8,
    unpack_registers,
)
from mbtool.codec.record import record

REFERENCE_TYPE = 6
MAX_FILE = 0xFFFF
MAX_RECORD = 0x270F  # 9999
READ_BYTE_COUNT = (0x07, 0xF5)
WRITE_BYTE_COUNT = (0x09, 0xFB)
READ_GROUP_SIZE = 7  # ref type 1, file 2, record 2, length 2
MAX_READ_REPLY_BYTES = 0xF5  # the reply's byte count is bounded like the request's


def _check_place(file: int, record: int, length: int) -> None:
    """File 1..65535, records 0..9999 and the group inside the file: exception 02 otherwise."""
    if not 1 <= file <= MAX_FILE:
        raise RequestError(
            f"file number {file} is out of range 1..{MAX_FILE}", ExceptionCode.ILLEGAL_DATA_ADDRESS
        )
    if not 0 <= record <= MAX_RECORD:
        raise RequestError(
            f"record number {record} is out of range 0..{MAX_RECORD}", ExceptionCode.ILLEGAL_DATA_ADDRESS
        )
    if length < 1:
        raise RequestError(f"record length {length} is below 1", ExceptionCode.ILLEGAL_DATA_VALUE)
    if record + length > MAX_RECORD + 1:
        raise RequestError(
            f"record {record} + length {length} runs past record {MAX_RECORD}",
            ExceptionCode.ILLEGAL_DATA_ADDRESS,
        )


def _check_byte_count(count: int, limits: tuple[int, int], what: str) -> None:
    low, high = limits
    if not low <= count <= high:
        raise RequestError(
            f"{what} byte count {count} (0x{count:02X}) is out of range 0x{low:02X}..0x{high:02X}",
            ExceptionCode.ILLEGAL_DATA_VALUE,
        )


def _split(pdu: bytes, name: str) -> bytes:
    """The groups of a request (or of FC21's echo), checked against the byte count."""
    if len(pdu) < 2:
        raise DecodeError(f"{name}: PDU is shorter than its byte count field", pdu)
    need(pdu, 2 + pdu[1], name)
    return bytes(pdu[2:])


def _reference_type(ref: int) -> None:
    if ref != REFERENCE_TYPE:
        raise RequestError(f"reference type {ref} is not 6", ExceptionCode.ILLEGAL_DATA_ADDRESS)


# --- FC 20: Read File Record -------------------------------------------------------------


def _group_head(pdu: bytes, at: int, g: int) -> list[Field]:
    """A sub-request's head (spec §3, FC 20/21): reference type, file, record, length."""
    return [
        u8(pdu, at, f"group{g}.reference_type"),
        count16(pdu, at + 1, f"group{g}.file"),
        count16(pdu, at + 3, f"group{g}.record"),
        count16(pdu, at + 5, f"group{g}.length"),
    ]


@record
class FileRecordRequest:
    """One group of a read: ``length`` registers from ``record`` of ``file``."""

    file: int
    record: int
    length: int

    def __post_init__(self) -> None:
        _check_place(self.file, self.record, self.length)


@record
class ReadFileRecordResponse(Response):
    """FC 20 reply: byte count, then per group: length (1 + 2n), reference type 6, n registers."""

    function_code: ClassVar = 0x14

    records: tuple[tuple[int, ...], ...]

    def encode(self) -> bytes:
        body = b"".join(
            bytes([1 + 2 * len(values), REFERENCE_TYPE]) + pack_registers(values) for values in self.records
        )
        return bytes([self.function_code, len(body)]) + body

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        out = [u8(pdu, 1, "byte_count")]
        at, g = 2, 0
        while at + 2 <= len(pdu):
            length = pdu[at]
            out += [u8(pdu, at, f"group{g}.length"), u8(pdu, at + 1, f"group{g}.reference_type")]
            out += register_fields(pdu, at + 2, min(len(pdu), at + 1 + length), None, f"group{g}.register")
            at, g = at + 1 + max(length, 1), g + 1
        return out

    @classmethod
    def decode(cls, pdu: bytes) -> ReadFileRecordResponse:
        body = _split(pdu, "read file record reply")
        records = []
        at = 0
        while at < len(body):
            if at + 2 > len(body):
                raise DecodeError(f"read file record reply: group at byte {at + 2} is truncated", pdu)
            length, ref = body[at], body[at + 1]
            if ref != REFERENCE_TYPE:
                raise DecodeError(f"read file record reply: reference type {ref} is not 6", pdu)
            if length < 1 or length % 2 == 0:
                raise DecodeError(f"read file record reply: group length {length} is not 1 + 2n", pdu)
            end = at + 1 + length
            if end > len(body):
                raise DecodeError(
                    f"read file record reply: group of {length} bytes runs past the byte count {len(body)}",
                    pdu,
                )
            records.append(unpack_registers(body[at + 2 : end]))
            at = end
        return cls(tuple(records))


@register
@record
class ReadFileRecord(Request):
    function_code: ClassVar = 0x14
    name: ClassVar = "Read File Record"
    request_size: ClassVar = counted(1)
    response_size: ClassVar = counted(1)
    response_type: ClassVar = ReadFileRecordResponse

    groups: tuple[FileRecordRequest, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", tuple(self.groups))
        _check_byte_count(READ_GROUP_SIZE * len(self.groups), READ_BYTE_COUNT, self.name)
        reply = sum(2 + 2 * group.length for group in self.groups)
        if reply > MAX_READ_REPLY_BYTES:
            raise RequestError(
                f"the reply would carry {reply} bytes, more than 0x{MAX_READ_REPLY_BYTES:02X}",
                ExceptionCode.ILLEGAL_DATA_VALUE,
            )

    def encode_data(self) -> bytes:
        body = b"".join(
            struct.pack(">BHHH", REFERENCE_TYPE, group.file, group.record, group.length)
            for group in self.groups
        )
        return bytes([len(body)]) + body

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        out = [u8(pdu, 1, "byte_count")]
        at, g = 2, 0
        while at + 7 <= len(pdu):
            out += _group_head(pdu, at, g)
            at, g = at + 7, g + 1
        return out

    @classmethod
    def decode(cls, pdu: bytes) -> ReadFileRecord:
        body = _split(pdu, cls.name)
        _check_byte_count(len(body), READ_BYTE_COUNT, cls.name)
        if len(body) % READ_GROUP_SIZE:
            raise RequestError(f"byte count {len(body)} is not a multiple of {READ_GROUP_SIZE}")
        groups = []
        for at in range(0, len(body), READ_GROUP_SIZE):
            ref, file, record, length = struct.unpack_from(">BHHH", body, at)
            _reference_type(ref)
            groups.append(FileRecordRequest(file, record, length))
        return cls(tuple(groups))

    def check_response(self, response: ReadFileRecordResponse) -> None:
        got = tuple(len(values) for values in response.records)
        expected = tuple(group.length for group in self.groups)
        if got != expected:
            raise MismatchError(
                f"reply carries record groups of {_counts(got)} registers, expected {_counts(expected)}"
            )


def _counts(counts: tuple[int, ...]) -> str:
    """Register counts of record groups in words: 10, or 2, 3 and 4."""
    words = [str(count) for count in counts]
    if len(words) < 2:
        return words[0] if words else "no"
    return ", ".join(words[:-1]) + " and " + words[-1]


# --- FC 21: Write File Record, answered by an echo ------------------------------------------


@record
class FileRecord:
    """One group of a write: ``values`` into ``file`` from ``record`` on."""

    file: int
    record: int
    values: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", tuple(self.values))
        _check_place(self.file, self.record, len(self.values))
        for value in self.values:
            check_u16(value, "register value")

    def encode(self) -> bytes:
        head = struct.pack(">BHHH", REFERENCE_TYPE, self.file, self.record, len(self.values))
        return head + pack_registers(self.values)


@register
@record
class WriteFileRecord(Request, Response):
    function_code: ClassVar = 0x15
    name: ClassVar = "Write File Record"
    broadcastable: ClassVar = True  # a write: unit 0 reaches every device (spec §2)
    request_size: ClassVar = counted(1)
    response_size: ClassVar = counted(1)

    groups: tuple[FileRecord, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", tuple(self.groups))
        _check_byte_count(
            sum(7 + 2 * len(group.values) for group in self.groups), WRITE_BYTE_COUNT, self.name
        )

    def encode_data(self) -> bytes:
        body = b"".join(group.encode() for group in self.groups)
        return bytes([len(body)]) + body

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        out = [u8(pdu, 1, "byte_count")]
        at, g = 2, 0
        while at + 7 <= len(pdu):
            length = int.from_bytes(pdu[at + 5 : at + 7], "big")
            out += _group_head(pdu, at, g)
            out += register_fields(
                pdu, at + 7, min(len(pdu), at + 7 + 2 * length), None, f"group{g}.register"
            )
            at, g = at + 7 + 2 * length, g + 1
        return out

    @classmethod
    def decode(cls, pdu: bytes) -> WriteFileRecord:
        body = _split(pdu, cls.name)
        _check_byte_count(len(body), WRITE_BYTE_COUNT, cls.name)
        groups = []
        at = 0
        while at < len(body):
            if at + 7 > len(body):
                raise RequestError(f"{cls.name}: group header at byte {at + 2} is truncated")
            ref, file, record, length = struct.unpack_from(">BHHH", body, at)
            _reference_type(ref)
            end = at + 7 + 2 * length
            if end > len(body):
                raise RequestError(
                    f"{cls.name}: group of {length} registers runs past the byte count {len(body)}"
                )
            groups.append(FileRecord(file, record, unpack_registers(body[at + 7 : end])))
            at = end
        return cls(tuple(groups))

    def check_response(self, response: Response) -> None:
        self._echo_check(response)


WriteFileRecord.response_type = WriteFileRecord
