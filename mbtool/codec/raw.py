"""Any PDU at all, for ``mbtool raw``: the request is bytes the user typed.

A known function code borrows its own type's reply length, so an RTU reply ends
by implicit length as usual (spec §2).  An unknown one answers UNKNOWN, and
only silence (RTU) or the delimiter (ASCII) can end its reply.  The reply is
never refused for its content: it comes back as a ``RawResponse`` to be
decoded, as far as the codec can, by whoever shows it.
"""

from __future__ import annotations

from typing import ClassVar

from mbtool.codec.errors import DecodeError, ProtocolError, RequestError
from mbtool.codec.pdu import UNKNOWN, ExceptionResponse, Request, Response, function_type
from mbtool.codec.record import record


@record
class RawResponse(Response):
    """A reply PDU kept as bytes."""

    function_code: ClassVar = 0  # unused: the reply's own code is pdu[0]

    pdu: bytes

    def encode(self) -> bytes:
        return self.pdu

    @classmethod
    def decode(cls, pdu: bytes) -> RawResponse:
        return cls(bytes(pdu))


@record
class RawRequest(Request):
    name: ClassVar = "Raw PDU"
    broadcastable: ClassVar = True  # the user decides; raw is for experiments

    pdu: bytes

    def __post_init__(self) -> None:
        if not self.pdu:
            raise RequestError("a raw request needs at least a function code")
        if len(self.pdu) > 253:
            raise RequestError(f"a PDU is at most 253 bytes, not {len(self.pdu)}")
        object.__setattr__(self, "pdu", bytes(self.pdu))

    @property
    def function_code(self) -> int:  # type: ignore[override]  # per request (its first byte), not per class
        return self.pdu[0]

    def encode(self) -> bytes:
        return self.pdu

    def encode_data(self) -> bytes:
        return self.pdu[1:]

    @classmethod
    def decode(cls, pdu: bytes) -> RawRequest:
        return cls(bytes(pdu))

    def known(self) -> Request | None:
        """The typed request these bytes make, if the codec knows and accepts them."""
        kind = function_type(self.function_code)
        if kind is None:
            return None
        try:
            return kind.decode(self.pdu)
        except ProtocolError:
            return None

    @property
    def expects_response(self) -> bool:
        typed = self.known()
        return typed.expects_response if typed is not None else True

    def response_length(self, pdu: bytes) -> int | None:
        if pdu and pdu[0] == self.function_code | 0x80:
            return 2
        typed = self.known()
        if typed is not None:
            return typed.response_length(pdu)
        kind = function_type(self.function_code)
        return kind.response_size.of(pdu) if kind is not None else UNKNOWN

    def decode_response(self, pdu: bytes) -> RawResponse | ExceptionResponse:
        if not pdu:
            raise DecodeError("empty response PDU", pdu)
        if pdu[0] == self.function_code | 0x80 and len(pdu) == 2:
            return ExceptionResponse.decode(pdu)
        return RawResponse(bytes(pdu))
