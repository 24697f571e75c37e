"""Read Device Identification: FC 43 with MEI type 0x0E (spec §3).

Not in the seeds, but in the current Modbus spec and on most modern devices.
Objects are (id, value) pairs: 0x00..0x02 basic (mandatory), 0x03..0x06
regular, 0x80..0xFF extended (device specific).  A device that cannot fit all
objects in one reply sets more-follows and the id to ask for next.
"""

from __future__ import annotations

from enum import IntEnum
from typing import ClassVar

from mbtool.codec.errors import DecodeError, MismatchError, RequestError
from mbtool.codec.pdu import (
    MAX_PDU,
    UNKNOWN,
    ExceptionCode,
    Field,
    Request,
    Response,
    need,
    register,
    text_of,
    u8,
)
from mbtool.codec.record import record

MEI_TYPE = 0x0E  # Read Device Identification; 0x0D (CANopen) is not supported
MORE_FOLLOWS = 0xFF
NO_MORE = 0x00
HEADER = 7  # function, MEI type, read code, conformity, more follows, next object id, object count


class ReadDeviceIdCode(IntEnum):
    BASIC = 0x01  # stream access to the basic objects
    REGULAR = 0x02  # stream access to the regular objects
    EXTENDED = 0x03  # stream access to the extended objects
    SPECIFIC = 0x04  # one object, individual access


OBJECT_NAMES = {
    0x00: "VendorName",
    0x01: "ProductCode",
    0x02: "MajorMinorRevision",
    0x03: "VendorUrl",
    0x04: "ProductName",
    0x05: "ModelName",
    0x06: "UserApplicationName",
}

CONFORMITY_LEVELS = {
    0x01: "basic identification (stream access only)",
    0x02: "regular identification (stream access only)",
    0x03: "extended identification (stream access only)",
    0x81: "basic identification (stream and individual access)",
    0x82: "regular identification (stream and individual access)",
    0x83: "extended identification (stream and individual access)",
}


def conformity_name(level: int) -> str:
    return CONFORMITY_LEVELS.get(level, f"unknown conformity level {level:02X}")


def object_name(object_id: int) -> str:
    if object_id in OBJECT_NAMES:
        return OBJECT_NAMES[object_id]
    if object_id >= 0x80:
        return f"Private{object_id:02X}"  # extended objects are device specific
    return f"Reserved{object_id:02X}"


@record
class _RequestSize:
    """FC43 requests are 4 bytes for MEI type 0x0E; any other MEI type is not ours to measure."""

    def of(self, pdu: bytes) -> int | None:
        if len(pdu) < 2:
            return None
        return 4 if pdu[1] == MEI_TYPE else UNKNOWN


@record
class _ResponseSize:
    """An FC43/0E reply's length is the header plus each object's id, length and value.

    None until the bytes that tell it have arrived; once the walk passes the
    largest PDU it stops and reports that (too long) length.
    """

    def of(self, pdu: bytes) -> int | None:
        if len(pdu) < 2:
            return None
        if pdu[1] != MEI_TYPE:
            return UNKNOWN
        if len(pdu) < HEADER:
            return None
        at = HEADER
        for _ in range(pdu[HEADER - 1]):
            if at > MAX_PDU:
                break
            if len(pdu) < at + 2:
                return None
            at += 2 + pdu[at + 1]
        return at


@record
class DeviceIdentificationResponse(Response):
    """FC 43/0E reply: read code, conformity level, more follows, next object id, objects."""

    function_code: ClassVar = 0x2B

    read_code: int
    conformity: int
    more_follows: bool
    next_object_id: int
    objects: tuple[tuple[int, bytes], ...]

    @property
    def conformity_name(self) -> str:
        return conformity_name(self.conformity)

    def named_objects(self) -> tuple[tuple[str, bytes], ...]:
        return tuple((object_name(object_id), value) for object_id, value in self.objects)

    def encode(self) -> bytes:
        head = bytes(
            [
                self.function_code,
                MEI_TYPE,
                self.read_code,
                self.conformity,
                MORE_FOLLOWS if self.more_follows else NO_MORE,
                self.next_object_id,
                len(self.objects),
            ]
        )
        return head + b"".join(bytes([object_id, len(value)]) + value for object_id, value in self.objects)

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        fields = [
            u8(pdu, 1, "mei_type", f"0x{pdu[1]:02X}"),
            u8(pdu, 2, "read_device_id_code"),
            u8(pdu, 3, "conformity_level", f"0x{pdu[3]:02X} {CONFORMITY_LEVELS.get(pdu[3], 'unknown')}"),
            u8(pdu, 4, "more_follows", "yes" if pdu[4] else "no"),
            u8(pdu, 5, "next_object_id", f"0x{pdu[5]:02X}"),
            u8(pdu, 6, "number_of_objects"),
        ]
        at = 7
        for _ in range(pdu[6]):
            object_id, length = pdu[at], pdu[at + 1]
            value = bytes(pdu[at + 2 : at + 2 + length])
            fields.append(Field(object_name(object_id), bytes(pdu[at : at + 2 + length]), text_of(value)))
            at += 2 + length
        return fields

    @classmethod
    def decode(cls, pdu: bytes) -> DeviceIdentificationResponse:
        if len(pdu) < HEADER:
            raise DecodeError(f"device identification reply is shorter than its {HEADER}-byte header", pdu)
        if pdu[1] != MEI_TYPE:
            raise DecodeError(f"MEI type {pdu[1]:02X} is not 0E (read device identification)", pdu)
        objects = []
        at = HEADER
        for index in range(pdu[HEADER - 1]):
            if len(pdu) < at + 2:
                raise DecodeError(f"device identification reply ends inside object #{index}", pdu)
            length = pdu[at + 1]
            if len(pdu) < at + 2 + length:
                raise DecodeError(f"object {pdu[at]:02X} of {length} bytes runs past the reply", pdu)
            objects.append((pdu[at], bytes(pdu[at + 2 : at + 2 + length])))
            at += 2 + length
        need(pdu, at, "device identification reply")
        read_code, conformity, more, next_id = pdu[2], pdu[3], pdu[4], pdu[5]
        warnings = []
        if not 1 <= read_code <= 4:
            warnings.append(f"read device id code {read_code:02X} is not 01..04")
        if conformity not in CONFORMITY_LEVELS:
            warnings.append(f"conformity level {conformity:02X} is not one the spec defines")
        if more not in (MORE_FOLLOWS, NO_MORE):
            warnings.append(f"more-follows byte {more:02X} is neither 00 nor FF")
        return cls(read_code, conformity, more != NO_MORE, next_id, tuple(objects), warnings=tuple(warnings))


@register
@record
class ReadDeviceIdentification(Request):
    """FC 43 / MEI 0x0E.  Stream access (codes 1-3) starts at ``object_id``; code 4 reads one object."""

    function_code: ClassVar = 0x2B
    name: ClassVar = "Read Device Identification"
    request_size: ClassVar = _RequestSize()
    response_size: ClassVar = _ResponseSize()
    response_type: ClassVar = DeviceIdentificationResponse

    read_code: int = ReadDeviceIdCode.BASIC
    object_id: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.read_code <= 4:
            raise RequestError(
                f"read device id code {self.read_code} is out of range 1..4", ExceptionCode.ILLEGAL_DATA_VALUE
            )
        object.__setattr__(self, "read_code", ReadDeviceIdCode(self.read_code))
        if not 0 <= self.object_id <= 0xFF:
            raise RequestError(
                f"object id {self.object_id} is out of range 0..255", ExceptionCode.ILLEGAL_DATA_ADDRESS
            )

    def encode_data(self) -> bytes:
        return bytes([MEI_TYPE, self.read_code, self.object_id])

    @classmethod
    def dissect(cls, pdu: bytes, request=None) -> list[Field]:
        codes = {1: "basic", 2: "regular", 3: "extended", 4: "one specific object"}
        return [
            u8(pdu, 1, "mei_type", f"0x{pdu[1]:02X} read device identification"),
            u8(pdu, 2, "read_device_id_code", f"{pdu[2]} {codes.get(pdu[2], 'invalid')}"),
            u8(pdu, 3, "object_id", f"0x{pdu[3]:02X} {OBJECT_NAMES.get(pdu[3], '')}".strip()),
        ]

    @classmethod
    def decode(cls, pdu: bytes) -> ReadDeviceIdentification:
        if len(pdu) >= 2 and pdu[1] != MEI_TYPE:
            raise RequestError(f"MEI type {pdu[1]:02X} is not supported", ExceptionCode.ILLEGAL_FUNCTION)
        need(pdu, 4, cls.name)
        return cls(pdu[2], pdu[3])

    def check_response(self, response: DeviceIdentificationResponse) -> None:
        if response.read_code != self.read_code:
            raise MismatchError(
                f"reply has read code {response.read_code:02X}, expected {self.read_code:02X}"
            )
        if self.read_code == ReadDeviceIdCode.SPECIFIC:
            ids = tuple(object_id for object_id, _ in response.objects)
            if ids != (self.object_id,):
                raise MismatchError(
                    f"individual access to object {self.object_id:02X} answered with objects"
                    f" {' '.join(f'{i:02X}' for i in ids) or 'none'}"
                )
