"""RTU (spec §2): ``[unit][PDU][CRC lo][CRC hi]``, ended by the PDU's implicit length or by
3.5 characters of silence, with no start mark: a frame amid garbage is found by the resync
(``codec/resync.py``).  The master's framer reads replies, the device's requests.
"""

from __future__ import annotations

import re

from mbtool.codec.checksum import crc16, crc_ok
from mbtool.codec.errors import ChecksumError, FrameError, function_code_text
from mbtool.codec.framer import Event, Frame, Framer
from mbtool.codec.pdu import MAX_PDU, UNKNOWN, Request, function_type, is_known
from mbtool.codec.resync import FRAME, NO_FRAME, FrameSearch, Verdict

RTU_MAX_ADU = 256
# A Modbus TCP header and the unit after it (MBAP: transaction id, protocol id, length, unit).
MBAP_HEADER_AND_UNIT = 7
MODBUS_TCP_DEVICE = "the device speaks Modbus TCP: leave --framer out"


def crc_verdict(adu: bytes) -> str:
    """An RTU frame's CRC in words, as --hex, decode and monitor show it: "CRC 0E 84 ok"."""
    if len(adu) < 3:
        return "CRC missing"
    # The expected value decides and is shown: one computation (crc_ok would refuse
    # the 3-byte frames a trace may show, and then contradict itself in words).
    expected = crc16(adu[:-2])
    if adu[-2] | adu[-1] << 8 == expected:
        return f"CRC {adu[-2]:02X} {adu[-1]:02X} ok"
    return f"CRC {adu[-2]:02X} {adu[-1]:02X} BAD, expected {expected & 0xFF:02X} {expected >> 8:02X}"


# Which offsets an RTU framer judges as frame starts, per (framer class, responses,
# function code asked, unit asked): see RtuFramer._start_rule.
_START_RULES: dict[tuple, re.Pattern[bytes]] = {}

# The size of a frame whose function code alone tells it, by code (0: the bytes after it or
# the request tell it; None: not yet worked out), per (responses, function code asked): see
# RtuFramer._sizes_for.
_FIXED_SIZES: dict[tuple, list[int | None]] = {}


def _byte_class(values: set[int]) -> bytes:
    """A regex character class matching exactly these byte values."""
    return b"[" + b"".join(re.escape(bytes([value])) for value in sorted(values)) + b"]"


class RtuFramer(Framer):
    """``[unit][PDU][CRC lo][CRC hi]``, ended by implicit length (or by silence)."""

    name = "rtu"
    checksum_name = "CRC"
    _held = False  # a corrupted frame is held: the awaited reply may begin in its last bytes
    _quiet = False  # inside silence(): no more bytes are coming
    _starved: tuple | None = None  # the state in which _parse last needed more bytes
    _marks: re.Pattern[bytes] | None = None  # the offsets worth judging amid garbage (_starts)

    def __init__(self, responses: bool = True) -> None:
        super().__init__(responses)
        self._fed = 0  # bytes fed so far: the resync's positions are absolute
        self._search = FrameSearch()
        # What the rules below were learnt for.  Nothing yet: the first look learns them for
        # what is expected then (a master's request), never first for nothing expected.
        self._scan_expect: Request | None = None
        self._scan_unit: int | None = -1

    def feed(self, data: bytes) -> None:
        super().feed(data)
        self._fed += len(data)

    pauses_end_frames = True  # a frame of unknown length (an unknown function code) ends so

    @property
    def waiting_for_silence(self) -> bool:
        if self._held and self._buffer:
            return True
        return len(self._buffer) >= 2 and self._pdu_length(bytes(self._buffer[1:])) == UNKNOWN

    def silence(self) -> Event | None:
        self._quiet = True
        try:
            return super().silence()
        finally:
            self._quiet = False

    def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes:
        body = bytes([unit]) + pdu
        return body + crc16(body).to_bytes(2, "little")

    def check(self, adu: bytes) -> str:
        return crc_verdict(adu)

    def _parse(self):
        # next_event() asks again after handing over the garbage; until bytes come or go
        # (or the request changes) the answer is the same: do not judge it all twice.
        state = (self._fed, len(self._buffer), self.expect, self.expect_unit, self._quiet)
        if state == self._starved:
            return None
        result = self._judge_front()
        self._starved = state if result is None else None
        return result

    def _judge_front(self):
        buf = self._buffer
        self._held = False
        self._rescan_if_expecting_anew()
        size = self._frame_size(0)
        if size is None:
            # The front does not tell its length yet: a whole frame may already sit behind it.
            return self._skip_to_frame(len(buf))
        if isinstance(size, FrameError):
            return self._garbage_up_to_a_start(1, size)
        if len(buf) < size:
            # Noise before a reply can look like the head of a long frame; without
            # this the real reply would wait inside that phantom frame until the deadline.
            return self._skip_to_frame(min(len(buf), size))
        if crc_ok(buf, 0, size):
            return self._whole(bytes(buf[:size]))
        # A bad checksum: either noise before a good frame that starts inside, or
        # a corrupted frame, reported whole (one line in the trace, not fragments).
        skip = self._skip_to_frame(size)
        if skip is not None:
            return skip
        if self._awaited_inside(size):
            self._held = True
            return None  # the reply we wait for may be starting inside: wait for the rest
        if self._silence_tells_corrupted():
            return None
        # Only the first rejection of a garbage run is reported (next_event folds the rest
        # into it): say what this one is only then.  Formatting the reason for every
        # corrupted would-be frame amid garbage cost as much as judging it.
        if self._garbage:
            return self._garbage_up_to_a_start(size, self._garbage_error)
        return self._modbus_tcp_answer() or self._garbage_up_to_a_start(size, self._whole(bytes(buf[:size])))

    def _modbus_tcp_answer(self) -> tuple[int, FrameError] | None:
        """(bytes to skip, why) when the front is a Modbus TCP device's answer to our RTU request
        (tcp:// with --framer rtu): the device read the request as an MBAP header, its unit and
        function code the transaction id, its next two bytes (0) the protocol id, and answered
        with that header and the unit it read (the request's seventh byte), whole (a PDU of
        two bytes at least: a corrupted echo of a write is not taken for one).  The whole MBAP
        frame is rejected as one, saying so, rather than a CRC error over its first bytes."""
        buf, expect, unit = self._buffer, self.expect, self.expect_unit
        if expect is None or unit is None or len(buf) < MBAP_HEADER_AND_UNIT or buf[2] or buf[3]:
            return None
        size = MBAP_HEADER_AND_UNIT + (buf[4] << 8 | buf[5]) - 1
        if not MBAP_HEADER_AND_UNIT + 2 <= size <= len(buf) or size > MBAP_HEADER_AND_UNIT + MAX_PDU:
            return None
        asked = self.build(unit, expect.encode())
        # (A request shorter than a header and a unit is no MBAP request to anyone.)
        if len(asked) < MBAP_HEADER_AND_UNIT or buf[:2] != asked[:2] or buf[6] != asked[6]:
            return None
        reply = bytes(buf[:size])
        return size, FrameError(
            f"a Modbus TCP reply to the RTU request: {reply.hex(' ').upper()} is an MBAP header with "
            f"the request's first bytes as transaction id and protocol id 0: {MODBUS_TCP_DEVICE}",
            reply,
        )

    def _silence_tells_corrupted(self) -> bool:
        """A whole frame with a bad CRC at the front: is it held until silence, not skipped?"""
        return False

    # -- resync (spec §2: an RTU frame has no start mark; only its length rule and CRC tell) --

    def _start_rule(self, expect: Request | None, unit: int | None) -> re.Pattern[bytes]:
        """Decide which offsets are worth judging as the start of a frame.

        While a request is outstanding: an offset holding its unit, or one byte before its
        function code (or code | 0x80).  That finds the reply, and a reply from the wrong
        unit or with the wrong function, reported as a mismatch; any other frame amid
        garbage cannot answer the request and stays garbage.  Judging every offset in
        Python made 64 KiB of garbage cost over 100 ms.

        With no request outstanding: one byte before any function code that can start a
        frame (an exception reply too).  The offsets left out are those the front would
        reject one by one as an unknown function code, so skipping them changes nothing
        (a device holds one until an ADU follows it: see DeviceRtuFramer._first_unsettled).
        """
        code = None if expect is None else expect.function_code
        key = (type(self), self.responses, code, unit)
        if key not in _START_RULES:  # once per request kind, not per request: a poll repeats them
            if code is not None:
                codes = {code, code | 0x80}
                units = set() if unit is None else {unit}
            else:
                codes = {code for code in range(256) if self._can_start(code)}
                units = set()
            # A look-ahead matches, at each offset worth judging, its unit or the function code
            # after it: the offsets are found in C, never byte by byte in Python.
            marks = [b"." + _byte_class(codes)] if codes else []
            if units:
                marks.insert(0, _byte_class(units) + b".")  # a unit byte with a function code after it
            _START_RULES[key] = re.compile(b"(?s)(?=" + b"|".join(marks) + b")")
        return _START_RULES[key]

    def _sizes_for(self, expect: Request | None) -> None:
        """Learn which function codes tell their frame's size alone: most do, and looking it up
        spares _frame_size the general rule for each offset judged amid garbage.  A code's size
        is worked out when a frame first seems to start with it (_fixed_size): asking about
        every code at once imported every function module, most of an RTU read's start-up."""
        code = None if expect is None else expect.function_code
        key = (self.responses, code)
        if key not in _FIXED_SIZES:
            _FIXED_SIZES[key] = [None] * 256
        self._fixed_sizes = _FIXED_SIZES[key]
        self._sizes_asked = code

    def _fixed_size(self, byte: int) -> int:
        """The size of a frame whose function code is ``byte``, if the code alone tells it; else 0."""
        if self.responses and byte & 0x80:
            length = 2  # an exception reply (pdu_length)
        elif byte == self._sizes_asked or (kind := function_type(byte)) is None:
            length = 0  # the request asked may refine its rule; an unknown code has none
        else:
            rule = kind.response_size if self.responses else kind.request_size
            length = getattr(rule, "fixed", None) or 0  # a Size, or a rule of its own
        return 1 + length + 2 if 0 < length <= MAX_PDU else 0

    def _can_start(self, code: int) -> bool:
        """Can a frame whose function code is ``code`` start here, with no request outstanding?"""
        if self.responses and code & 0x80:
            return True  # an exception reply, whatever its function
        return is_known(code)

    def _starts(self, lo: int, hi: int):
        """The offsets in lo..hi-1 worth judging as the start of a frame, in order."""
        if self._marks is None:  # compiled (up to 2.5 M instructions) once garbage needs it
            self._marks = self._start_rule(self._scan_expect, self._scan_unit)
        # Up to hi inclusive: the function code of an offset at hi - 1 lies at hi.
        return map(re.Match.start, self._marks.finditer(self._buffer, lo, hi + 1))

    def _rescan_if_expecting_anew(self) -> None:
        if self._scan_expect is not self.expect or self._scan_unit != self.expect_unit:
            # Lengths and the offsets worth judging depend on the request: judge afresh.
            self._scan_expect, self._scan_unit = self.expect, self.expect_unit
            self._marks = None  # _start_rule's, for this request: a clean reply never needs it
            self._sizes_for(self.expect)
            self._search.reset()

    def _garbage_up_to_a_start(self, skip: int, error: Frame | FrameError | None):
        """(bytes to skip, why) for a rejected front, stretched over the offsets behind it
        that are not worth judging, so garbage goes in one step, not byte by byte."""
        last = self._first_unsettled()
        if skip < last:
            skip = next(self._starts(skip, last), last)
        return skip, error

    def _first_unsettled(self) -> int:
        """Where stretching garbage stops: from this offset on, one that _starts leaves out may
        still start a frame once more bytes come.  Here only the last byte, whose function
        code has not arrived."""
        return len(self._buffer) - 1

    def _frame_size(self, start: int) -> int | None | FrameError:
        """Size of the frame that would start at ``start``: None for more bytes, or why none can."""
        buf = self._buffer
        if len(buf) < start + 2:
            return None
        code = buf[start + 1]
        size = self._fixed_sizes[code]
        if size is None:
            size = self._fixed_sizes[code] = self._fixed_size(code)
        if size:
            return size  # the function code alone tells it
        # A window of one maximal ADU is all a length can depend on; never copy the
        # whole buffer per byte (64 KiB of garbage would cost quadratic time).
        length = self._pdu_length(bytes(buf[start + 1 : start + RTU_MAX_ADU]))
        if length is None:
            return None
        if length == UNKNOWN:
            return self._unknown_function_size(start)
        if length > MAX_PDU:
            return FrameError(f"PDU length {length} exceeds {MAX_PDU}", bytes(buf[start : start + 2]))
        return 1 + length + 2

    def _unknown_function_size(self, start: int) -> None | FrameError:
        """_frame_size for a function code the codec does not know: None if only silence can end
        the frame, or why none starts here."""
        code = self._buffer[start + 1]
        if self.expect is not None and code in (self.expect.function_code, self.expect.function_code | 0x80):
            return None  # an unknown function code we asked for (raw): only silence ends it
        return FrameError(f"{function_code_text(code)} is unknown", bytes(self._buffer[start : start + 2]))

    def _skip_to_frame(self, end: int):
        """(bytes to skip, why) if a whole, valid frame starts at an offset in 1..end-1.

        Only the offsets _starts picks out are judged.  An offset is picked out by its byte
        and the next one: the last byte waits for its follower (no whole frame can start
        there yet anyway).
        """
        buf = self._buffer
        base = self._fed - len(buf)  # the absolute position of buf[0]
        found = self._search.find(base, self._fed, end, min(end, len(buf) - 1), self._frame_at, self._starts)
        return None if found is None else self._noise(found)

    def _frame_at(self, start: int) -> Verdict | int:
        """Does a whole, valid frame start here: FRAME, NO_FRAME, or (an int) how many bytes
        must have been fed before more bytes can tell (FrameSearch)."""
        buf = self._buffer
        base = self._fed - len(buf)
        if self.responses and start + 2 <= len(buf):
            code = buf[start + 1]
            if code & 0x80:
                # An exception reply, half of all garbage bytes: 5 bytes, whatever was asked.
                if start + 5 > len(buf):
                    return base + start + 5
                return FRAME if crc_ok(buf, start, 5) else NO_FRAME
            if not is_known(code) and (self.expect is None or code != self.expect.function_code):
                return NO_FRAME  # a code nobody knows or asked for starts no frame
        size = self._frame_size(start)
        if size is None:
            return self._fed + 1  # the bytes that tell its length have not all come
        if not isinstance(size, int):
            return NO_FRAME
        if start + size > len(buf):
            return base + start + size
        return FRAME if crc_ok(buf, start, size) else NO_FRAME

    def _noise(self, start: int):
        return start, FrameError(f"{start} bytes of noise before a frame", bytes(self._buffer[:start]))

    def _awaited_inside(self, end: int) -> bool:
        """Does the awaited reply seem to start at an offset in 1..end-1, not yet complete?"""
        if self.expect is None or self._quiet:
            return False
        if self.expect_unit is None:
            # Offsets are picked out by the function code after them, which the last byte lacks.
            last = end == len(self._buffer) and self._awaited(end - 1)
            return last or any(self._awaited(start) for start in self._starts(1, end))
        unit = bytes([self.expect_unit])  # the reply starts with it: find it in C
        start = self._buffer.find(unit, 1, end)
        while start >= 0:
            if self._awaited(start):
                return True
            start = self._buffer.find(unit, start + 1, end)
        return False

    def _awaited(self, start: int) -> bool:
        """Does the reply to the expected request seem to start here, not yet complete?"""
        if self.expect is None or self._quiet:
            return False
        if self.expect_unit is not None and self._buffer[start] != self.expect_unit:
            return False
        if start + 1 >= len(self._buffer):
            return True  # its function code has not arrived: only more bytes or silence can tell
        code = self._buffer[start + 1]
        if code not in (self.expect.function_code, self.expect.function_code | 0x80):
            return False
        size = self._frame_size(start)
        return size is None or (isinstance(size, int) and start + size > len(self._buffer))

    def _whole(self, data: bytes) -> Frame | FrameError:
        if len(data) < 4:
            return FrameError(f"truncated frame ({len(data)} bytes)", data)
        received = int.from_bytes(data[-2:], "little")
        expected = crc16(data[:-2])
        if received != expected:
            length = self._pdu_length(data[1:RTU_MAX_ADU])
            if length is not None and length != UNKNOWN and 1 + length + 2 > len(data):
                # Silence came before the length the frame announces: its end never came,
                # and "CRC error" would send the user looking for noise.
                return FrameError(f"truncated frame ({len(data)} of {1 + length + 2} bytes)", data)
            return ChecksumError(
                f"CRC error: frame {data.hex(' ').upper()} carries {data[-2]:02X} {data[-1]:02X},"
                f" expected {expected & 0xFF:02X} {expected >> 8:02X}",
                data,
                received,
                expected,
            )
        return Frame(data[0], data[1:-2], data)


class DeviceRtuFramer(RtuFramer):
    """Reads requests like a slave: a frame with a function code the codec does not know is
    ended by silence and answered with exception 01, not skipped byte by byte as noise."""

    def __init__(self) -> None:
        super().__init__(responses=False)

    # Resync: an unknown function code may start a request that only silence ends (spec §2:
    # 3.5 character times end an RTU frame), until more than one maximal ADU has come behind
    # it.  Behind the front it is not judged at all (_can_start is RtuFramer's): before
    # silence it is never a whole frame, so never the frame found behind noise.  Judging it
    # kept nearly every offset pending, each rechecked at every step: 64 KiB took seconds.

    def _first_unsettled(self) -> int:
        # Garbage is stretched over unknown function codes only where an ADU follows them:
        # the front rejects those one by one (_unknown_function_size), not the later ones.
        return len(self._buffer) - RTU_MAX_ADU

    def _unknown_function_size(self, start: int) -> None | FrameError:
        # A function code the codec does not know starts a request that silence will end,
        # answered with exception 01.  Beyond one maximal ADU it cannot be a frame: skip it as
        # noise, which also keeps the buffer (and the work silence() does on it) bounded.
        # (A known code with a length the codec cannot tell, FC43 with another MEI type, is noise.)
        if len(self._buffer) - start <= RTU_MAX_ADU and not is_known(self._buffer[start + 1]):
            return None
        return super()._unknown_function_size(start)

    def _silence_tells_corrupted(self) -> bool:
        # A bad CRC at the length a request would have: on a shared bus it is as likely
        # a reply from another slave, or a longer FC08 query; only silence tells (spec §2).
        return not self._quiet and len(self._buffer) <= RTU_MAX_ADU

    def silence(self):
        if self._buffer and not self._garbage:
            frame = self._whole(bytes(self._buffer))
            if isinstance(frame, Frame):
                self._buffer.clear()
                return frame
        return super().silence()
