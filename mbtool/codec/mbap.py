"""Modbus TCP (the Modbus TCP implementation guide): the MBAP header before the PDU, no checksum."""

from __future__ import annotations

import struct
from collections.abc import Callable

from mbtool.codec.checksum import crc_ok
from mbtool.codec.errors import FrameError
from mbtool.codec.framer import Frame, Framer, Prediction
from mbtool.codec.pdu import MAX_PDU, UNKNOWN

MBAP_HEADER = 7
# The MBAP header: transaction id, protocol id, length, unit (compiled once: one a frame).
_MBAP_HEADER = struct.Struct(">HHHB")
_MBAP_FIELDS = struct.Struct(">HHH")  # without the unit, which the frame takes with the PDU
_REPLY_FIELDS = struct.Struct(">HHB")  # after the transaction id: protocol id, length, unit


class TcpFramer(Framer):
    """MBAP: transaction id, protocol id 0, length (unit + PDU), unit; no checksum."""

    name = "tcp"
    checksum_name = "MBAP"
    # The Modbus TCP implementation guide: over TCP the unit id only routes through a
    # gateway; 0 and FF address the server itself, which answers.  No broadcast.
    broadcast_unit = None

    def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes:
        return _MBAP_HEADER.pack(transaction_id, 0, len(pdu) + 1, unit) + pdu

    def frames(self, unit: int, pdu: bytes) -> Callable[[int], bytes]:
        rest = self.build(unit, pdu)[2:]  # all but the transaction id, the same every attempt
        return lambda transaction_id: transaction_id.to_bytes(2, "big") + rest

    def predict(self, unit: int, prefix: tuple[bytes, int] | None) -> Prediction | None:
        if prefix is None:
            return None
        head, length = prefix
        # The request's transaction id, then protocol 0, the length, the unit and the PDU's head.
        return Prediction(
            2, _REPLY_FIELDS.pack(0, length + 1, unit) + head, MBAP_HEADER + length, MBAP_HEADER
        )

    def check(self, adu: bytes) -> str:
        if len(adu) < MBAP_HEADER:
            return "MBAP header truncated"
        tid, pid, length = _MBAP_FIELDS.unpack_from(adu)
        verdict = "ok" if pid == 0 and length == len(adu) - 6 else "BAD"
        return f"MBAP tid {tid} length {length} {verdict}"

    def _parse(self):
        buf = self._buffer
        if len(buf) < MBAP_HEADER:
            return None
        tid, pid, length = _MBAP_FIELDS.unpack_from(buf)
        if pid != 0:
            # Noise: no frame starts before the next 00 00 that could be a protocol id, so
            # skip to it at once, not byte by byte (a flooding peer must not outrun the resync).
            found = buf.find(b"\x00\x00", 3)
            skip = found - 2 if found != -1 else max(1, len(buf) - 3)
            return skip, self._not_mbap(f"MBAP protocol id {pid}, expected 0")
        if not 2 <= length <= MAX_PDU + 1:
            return 1, self._not_mbap(f"MBAP length {length} is outside 2..{MAX_PDU + 1}")
        size = 6 + length
        if len(buf) < size:
            return None
        adu = bytes(buf[:size])
        return Frame(adu[6], adu[7:], adu, tid)

    def _whole(self, data: bytes) -> Frame | FrameError:
        return FrameError(f"truncated MBAP frame ({len(data)} bytes)", data)

    def _not_mbap(self, why: str) -> FrameError:
        """A bad MBAP header at the front.  When the bytes there are a whole RTU frame with a
        good CRC, say so: the peer is an RTU-over-TCP gateway, the commonest reason for it."""
        buf = self._buffer
        if not self._garbage:  # only the first bad byte of a run is reported: look only there
            size = self._pdu_length(bytes(buf[1:]))
            if size is not None and size != UNKNOWN and crc_ok(buf, 0, size + 3):
                why += " (an RTU frame with a good CRC: an RTU-over-TCP gateway? try --framer rtu)"
        return FrameError(why, bytes(buf[:MBAP_HEADER]))
