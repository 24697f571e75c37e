"""ASCII (spec §2): ``:``, the unit and the PDU in hex, the LRC, CR LF."""

from __future__ import annotations

import binascii

from mbtool.codec.checksum import lrc
from mbtool.codec.errors import ChecksumError, FrameError
from mbtool.codec.framer import Frame, Framer

ASCII_MAX_CHARS = 513  # ':' + 2 × 255 hex + CR LF (spec §2)


class AsciiFramer(Framer):
    """``:`` hex(unit PDU) hex(LRC) CR LF; LF may be changed by FC08 sub-function 03."""

    name = "ascii"
    checksum_name = "LRC"

    def __init__(self, responses: bool = True, delimiter: int = 0x0A) -> None:
        super().__init__(responses)
        self.delimiter = delimiter

    def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes:
        body = bytes([unit]) + pdu
        text = (body + bytes([lrc(body)])).hex().upper().encode()
        return b":" + text + b"\r" + bytes([self.delimiter])

    def check(self, adu: bytes) -> str:
        try:
            body = binascii.unhexlify(adu.strip(b":\r\n" + bytes([self.delimiter])))
        except (binascii.Error, ValueError):
            return "LRC unreadable (not hex)"
        if len(body) < 2:
            return "LRC missing"
        expected = lrc(body[:-1])
        if body[-1] == expected:
            return f"LRC {expected:02X} ok"
        return f"LRC {body[-1]:02X} BAD, expected {expected:02X}"

    def _parse(self):
        buf = self._buffer
        if not buf:
            return None
        start = buf.find(b":")
        if start < 0:
            return len(buf), FrameError(f"{len(buf)} bytes before any ':'", bytes(buf))
        if start > 0:
            return start, FrameError(f"{start} bytes before ':'", bytes(buf[:start]))
        end = buf.find(bytes([self.delimiter]))
        restart = buf.find(b":", 1)
        if 0 < restart and (end < 0 or restart < end):
            # A new ':' before the end: the device restarts on ':' (spec §2), and so do we.
            return restart, FrameError("frame abandoned by a new ':'", bytes(buf[:restart]))
        if end < 0:
            if len(buf) > ASCII_MAX_CHARS:
                return len(buf), FrameError(
                    f"no end of frame within {ASCII_MAX_CHARS} characters", bytes(buf)
                )
            return None
        frame = self._whole(bytes(buf[: end + 1]))
        if isinstance(frame, Frame):
            return frame
        return end + 1, frame

    def _whole(self, data: bytes) -> Frame | FrameError:
        if not data.startswith(b":") or not data.endswith(b"\r" + bytes([self.delimiter])):
            return FrameError("ASCII frame not ended by CR LF", data)
        text = data[1:-2]
        if len(text) % 2:
            return FrameError(f"odd number of hex characters ({len(text)})", data)
        try:
            body = binascii.unhexlify(text)
        except (binascii.Error, ValueError):
            return FrameError("non-hex characters in ASCII frame", data)
        if len(body) < 3:
            return FrameError(f"ASCII frame too short ({len(body)} bytes)", data)
        expected = lrc(body[:-1])
        if body[-1] != expected:
            return ChecksumError(
                f"LRC error: frame {data.decode('ascii', 'replace').strip()} carries {body[-1]:02X}, expected {expected:02X}",
                data,
                body[-1],
                expected,
            )
        return Frame(body[0], body[1:-1], data)
