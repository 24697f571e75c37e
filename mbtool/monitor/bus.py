"""A passive bus monitor, sans-IO: bytes with their arrival times in, frames out.

A master's framer reads only replies and a device's only requests; on the bus both
go by, so every RTU frame is tried as a request and as a response by the codec's
implicit lengths (spec §2), the likelier reading first: after a request, a frame
from the same unit with the same function code (or its exception) is read as its
response.  Implicit length is the primary splitter, because the pauses the OS lets
us see are coarse (USB adapters deliver bytes in bursts of several ms); silence
(``silence`` seconds without a byte, t3.5 on a real UART, spec §2) ends what the
length cannot: an unknown function code, a damaged frame, garbage, a frame cut short.
ASCII frames run from ':' to CR LF (the codec's AsciiFramer, spec §2).

The caller owns the clock and the port: ``feed(when, data)`` for every read,
``idle(now)`` when a read returned nothing, ``finish(now)`` at the end.  Each
returns what became clear: ``BusFrame`` records (frames and garbage runs, in line
order) and ``Unanswered`` notes for requests whose response never came (another
request followed, or ``response_timeout`` passed).  Every byte fed comes out in
exactly one BusFrame.
"""

from __future__ import annotations

from bisect import bisect_right

from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.checksum import crc_ok
from mbtool.codec.describe import Described, describe_pdu, split_frame
from mbtool.codec.errors import ChecksumError, ProtocolError
from mbtool.codec.framer import Frame
from mbtool.codec.pdu import MAX_PDU, UNKNOWN, function_type, load_all_functions, pdu_length
from mbtool.codec.record import record
from mbtool.codec.resync import FRAME, NO_FRAME, FrameSearch, Verdict
from mbtool.codec.rtu import RTU_MAX_ADU

MIN_RTU_FRAME = 4  # unit, function code, CRC: the FC07/11/12/17 requests (spec §2, §3)
GARBAGE_RUN = RTU_MAX_ADU  # a garbage run is reported at the latest when it is this long


@record
class BusFrame:
    """One frame on the line, or one run of garbage (``direction`` "garbage")."""

    number: int  # 1, 2, ... in line order; garbage runs are numbered too
    time: float  # arrival of its first byte, seconds since the epoch (untimed: when it was read)
    end: float  # arrival of its last byte
    gap: float | None  # seconds since the end of the previous frame; None for the first, or untimed
    framing: str  # rtu | ascii
    wire: bytes  # the exact bytes on the line
    direction: str  # request | response | garbage
    unit: int | None = None
    function: int | None = None  # as on the wire: an exception has 0x80 set
    checksum_ok: bool | None = None  # None for garbage
    checksum: str = ""  # the verdict, e.g. "CRC 76 87 ok"
    described: Described | None = None  # the decoded fields (codec.describe), None for garbage
    latency: float | None = None  # a response: seconds from the end of its request to its start, if timed
    request: int | None = None  # a response: the number of the request it answers
    flags: tuple[str, ...] = ()  # bad-checksum exception invalid unsolicited late broadcast garbage
    note: str = ""  # garbage: why the bytes are no frame


@record
class Unanswered:
    """A request that got no response: another request followed, or the timeout passed."""

    time: float  # when that became clear
    request: BusFrame
    reason: str


class Tally:
    """The counts of the summary line; the caller counts what it shows."""

    def __init__(self) -> None:
        self.frames = self.requests = self.responses = self.unanswered = 0
        self.exceptions = self.checksum_errors = self.garbage_bytes = 0

    def count(self, seen: BusFrame | Unanswered) -> None:
        if isinstance(seen, Unanswered):
            self.unanswered += 1
            return
        if seen.direction == "garbage":
            self.garbage_bytes += len(seen.wire)
            return
        self.frames += 1
        if seen.direction == "request":
            self.requests += 1
        else:
            self.responses += 1
        if "exception" in seen.flags:
            self.exceptions += 1
        if "bad-checksum" in seen.flags:
            self.checksum_errors += 1

    def __str__(self) -> str:
        return (
            f"frames {self.frames}, requests {self.requests}, responses {self.responses}, "
            f"unanswered {self.unanswered}, exceptions {self.exceptions}, "
            f"checksum errors {self.checksum_errors}, garbage bytes {self.garbage_bytes}"
        )


class BusMonitor:
    def __init__(
        self, framing: str = "rtu", silence: float = 0.02, response_timeout: float = 1.0, timed: bool = True
    ) -> None:
        """``timed``: the times fed are when the bytes came.  A recording of raw bytes has
        none: its frames are split by their implicit length alone, get no gap or latency,
        and a request is unanswered only when another follows it."""
        if framing not in ("rtu", "ascii"):
            raise ValueError(f"a bus monitor reads rtu or ascii, not {framing}")
        self.framing = framing
        self.timed = timed
        self.silence = silence
        self.response_timeout = response_timeout
        self._buffer = bytearray()  # RTU: bytes not yet judged
        self._ascii = AsciiFramer() if framing == "ascii" else None
        self._fed = 0  # bytes fed so far: stream positions are absolute
        self._taken = 0  # bytes handed out (frames and garbage) so far
        self._arrivals: list[int] = []  # stream position of each chunk's first byte...
        self._times: list[float] = []  # ...and when it arrived
        self._last_byte: float | None = None
        self._previous_end: float | None = None
        self._number = 0
        self._garbage = bytearray()  # the garbage run not yet handed out
        self._garbage_note = ""
        self._pending: BusFrame | None = None  # the request waiting for its response
        self._late: BusFrame | None = None  # timed out; its response may still come before the next request
        # Where a good frame starts inside the buffer: the framers' resync (FrameSearch).
        self._search = FrameSearch()
        # Every function module loaded now, not while the first frame is being read: the
        # codec loads a module on the first look-up of a code of it.
        load_all_functions()

    # -- what the caller calls ------------------------------------------------------------

    def feed(self, when: float, data: bytes, since: float | None = None) -> list[BusFrame | Unanswered]:
        """``data`` arrived at ``when`` (seconds since the epoch), and not before ``since``.

        A pause counts only if it was seen: a reader that was busy (or descheduled) finds
        bytes waiting that may have come long before it looked, so it passes the time of
        its previous read as ``since``, and only ``idle`` (a read that found nothing) ends
        a frame by silence.  Without ``since`` the bytes came at ``when`` (a recording).
        """
        out: list[BusFrame | Unanswered] = []
        if not data:
            return self.idle(when)
        since = when if since is None else since
        if self._buffered and self._last_byte is not None and since - self._last_byte >= self.silence:
            out += self._cut(quiet=True)  # the pause before these bytes ended what came before
        self._arrivals.append(self._fed)
        self._times.append(when)
        self._fed += len(data)
        self._last_byte = when
        if self._ascii is not None:
            self._ascii.feed(data)
        else:
            self._buffer += data
        out += self._cut(quiet=False)
        out += self._expire(when)
        return out

    def idle(self, now: float) -> list[BusFrame | Unanswered]:
        """A read returned nothing at ``now``: a long enough pause ends what is buffered."""
        out: list[BusFrame | Unanswered] = []
        if self._buffered and self._last_byte is not None and now - self._last_byte >= self.silence:
            out += self._cut(quiet=True)
        out += self._expire(now)
        return out

    def finish(self, now: float) -> list[BusFrame | Unanswered]:
        """The end of listening: what is buffered is judged as if the line fell silent."""
        out = self._cut(quiet=True) if self._buffered else []
        return out + self._expire(now)

    @property
    def _buffered(self) -> bool:
        return bool(self._buffer or self._garbage or (self._ascii is not None and self._ascii.buffered))

    # -- time -------------------------------------------------------------------------------

    def _time_at(self, position: int) -> float:
        index = bisect_right(self._arrivals, position) - 1
        return self._times[max(index, 0)]

    def _take(self, size: int) -> tuple[float, float]:
        """The arrival times of the next ``size`` bytes of the stream, which are now handed out."""
        start, end = self._taken, self._taken + max(size, 1) - 1
        self._taken += size
        times = self._time_at(start), self._time_at(end)
        # Chunks wholly handed out are no longer needed (keep the one the next byte is in).
        drop = bisect_right(self._arrivals, self._taken) - 1
        if drop > 0:
            del self._arrivals[:drop], self._times[:drop]
        return times

    def _expire(self, now: float) -> list[Unanswered]:
        pending = self._pending
        if pending is None or not self.timed or now - pending.end < self.response_timeout:
            return []
        self._pending, self._late = None, pending
        return [self._unanswered(pending.end + self.response_timeout, pending)]

    def _unanswered(self, when: float, request: BusFrame, followed: bool = False) -> Unanswered:
        if followed and not self.timed:
            reason = "another request followed"
        elif followed:
            reason = f"another request followed after {1000 * (when - request.end):.0f} ms"
        else:
            reason = f"no response within {1000 * self.response_timeout:.0f} ms"
        return Unanswered(when, request, reason)

    # -- splitting --------------------------------------------------------------------------

    def _cut(self, quiet: bool) -> list[BusFrame | Unanswered]:
        out: list[BusFrame | Unanswered] = []
        if self._ascii is not None:
            out += self._cut_ascii(quiet)
        else:
            while self._buffer:
                step = self._rtu_step(quiet)
                if step is None:
                    break
                size, direction, note = step
                if direction == "garbage":
                    if not self._garbage:
                        self._garbage_note = note
                    self._garbage += self._buffer[:size]
                    del self._buffer[:size]
                    if len(self._garbage) >= GARBAGE_RUN:
                        out += self._flush_garbage()
                    continue
                out += self._flush_garbage()
                wire = bytes(self._buffer[:size])
                del self._buffer[:size]
                out += self._observe(wire, direction)
        if quiet or (self._garbage and not self._buffer):
            out += self._flush_garbage()
        return out

    def _cut_ascii(self, quiet: bool) -> list[BusFrame | Unanswered]:
        framer = self._ascii
        assert framer is not None  # made for ASCII, the only framing cut here
        out: list[BusFrame | Unanswered] = []
        events = []
        while (event := framer.next_event()) is not None:
            events.append(event)
        while quiet and (event := framer.silence()) is not None:
            events.append(event)
        for event in events:
            if isinstance(event, Frame):
                out += self._observe(event.adu, None)
            elif isinstance(event.error, ChecksumError):
                # A whole frame with a bad LRC, and the framer may have run garbage on to it.
                size = len(event.error.data)
                out += self._observe(event.data[:size], None)
                if len(event.data) > size:
                    self._garbage += event.data[size:]
                    self._garbage_note = "not a frame"
                    out += self._flush_garbage()
            else:
                self._garbage += event.data
                self._garbage_note = str(event.error)
                out += self._flush_garbage()
        return out

    def _rtu_step(self, quiet: bool) -> tuple[int, str, str] | None:
        """(size, request|response|garbage, note) of what starts the buffer, or None: wait."""
        buf = self._buffer
        n = len(buf)
        if n < 2:
            return (n, "garbage", "a lone byte") if quiet else None
        readings = self._readings(0)
        waiting = False  # a reading of known length still lacks bytes
        for direction, size in readings:
            if size is None or size > n:
                waiting = True
            elif size != UNKNOWN and crc_ok(buf, 0, size):
                return size, direction, ""
        if quiet and n <= RTU_MAX_ADU and crc_ok(buf, 0, n):
            # Only silence ends a function code the codec does not know (spec §2).
            return n, self._guess(0), ""
        if quiet or not waiting:
            inner = self._frame_inside()
            if inner is not None:
                # Bytes before a good frame: a damaged frame if a reading fits them exactly.
                for direction, size in readings:
                    if size == inner and self._plausible(0):
                        return size, direction, ""
                return inner, "garbage", "not a frame: a good frame follows"
        if not quiet:
            if n > RTU_MAX_ADU:
                return 1, "garbage", "no frame starts here"  # no frame is longer
            return None
        # The line fell silent: what is here is all there is.
        if self._plausible(0):
            # The likelier reading decides: a frame with a bad CRC that spans all the bytes
            # before the silence, or a frame the silence cut short.
            for direction, size in readings:
                if size == n:
                    return size, direction, ""
                if size is None or size > n:
                    return n, "garbage", "a frame cut short by silence"
            for direction, size in readings:
                if size is not None and size != UNKNOWN and MIN_RTU_FRAME <= size < n:
                    return size, direction, ""
        return n, "garbage", "not a frame"

    def _readings(self, start: int) -> list[tuple[str, int | None]]:
        """The frame sizes that may start at ``start``, likelier first: (direction, size).

        size None: more bytes are needed to tell; UNKNOWN: only silence can end it.
        """
        buf = self._buffer
        unit, code = buf[start], buf[start + 1]
        pdu = bytes(buf[start + 1 : start + RTU_MAX_ADU])
        asked = self._asked(unit, code)
        if asked is not None:
            order = [("response", asked.described.request if asked.described else None), ("request", None)]
        else:
            order = [("request", None), ("response", None)]
        readings = []
        for direction, request in order:
            length = pdu_length(pdu, direction == "response", request)
            if length is None or length == UNKNOWN:
                readings.append((direction, length))
            elif 1 <= length <= MAX_PDU:
                readings.append((direction, 1 + length + 2))
        return readings

    def _frame_inside(self) -> int | None:
        """The first offset past 0 where a whole frame with a good CRC sits in the buffer."""
        n = len(self._buffer)
        return self._search.find(self._fed - n, self._fed, n, n - 1, self._frame_at, range)

    def _frame_at(self, start: int) -> Verdict | int:
        """FRAME: a whole frame with a good CRC starts here; NO_FRAME: none ever will; else
        the absolute stream position up to which bytes must come before it can be told."""
        n = len(self._buffer)
        base = self._fed - n
        wake = None
        for _, size in self._readings(start):
            if size == UNKNOWN:
                continue  # only silence could end it: not a frame inside a run of bytes
            if size is None or start + size > n:
                need = base + n + 1 if size is None else base + start + size
                wake = need if wake is None else min(wake, need)
            elif crc_ok(self._buffer, start, size):
                return FRAME
        return NO_FRAME if wake is None else wake

    def _plausible(self, start: int) -> bool:
        """Could a damaged frame start here: a function code (or its exception) the codec knows."""
        return function_type(self._buffer[start + 1] & 0x7F) is not None

    def _asked(self, unit: int | None, code: int) -> BusFrame | None:
        """The request a frame from ``unit`` with ``code`` would answer, if one is waiting."""
        for request in (self._pending, self._late):
            if request is not None and request.unit == unit and request.function == code & 0x7F:
                return request
        return None

    def _guess(self, start: int) -> str:
        return "response" if self._asked(self._buffer[start], self._buffer[start + 1]) else "request"

    # -- what a frame is --------------------------------------------------------------------

    def _flush_garbage(self) -> list[BusFrame]:
        if not self._garbage:
            return []
        wire = bytes(self._garbage)
        self._garbage.clear()
        note = self._garbage_note or "not a frame"
        start, end = self._take(len(wire))
        return [self._frame(start, end, wire, "garbage", flags=("garbage",), note=note)]

    def _frame(self, start: float, end: float, wire: bytes, direction: str, **details) -> BusFrame:
        self._number += 1
        gap = None
        if self._previous_end is not None and self.timed:
            gap = max(start - self._previous_end, 0.0)
        self._previous_end = end
        return BusFrame(self._number, start, end, gap, self.framing, wire, direction, **details)

    def _observe(self, wire: bytes, direction: str | None) -> list[BusFrame | Unanswered]:
        """A frame cut from the line: decode it, pair it with its request, flag what is wrong.

        ``direction``: the reading its length fitted (RTU), None to decide here (ASCII,
        or a frame that only silence ended).
        """
        start, end = self._take(len(wire))
        try:
            text = wire.decode("ascii") if self.framing == "ascii" else wire.hex()
            framing, adu, unit, pdu, ok, verdict = split_frame(text, self.framing)
        except (ProtocolError, UnicodeDecodeError) as error:
            return [self._frame(start, end, wire, "garbage", flags=("garbage",), note=str(error))]
        out: list[BusFrame | Unanswered] = []
        # A response that comes later than the timeout: its request is unanswered first.
        if self._pending is not None and self.timed and start - self._pending.end >= self.response_timeout:
            out += self._expire(start)
        code = pdu[0] if pdu else 0
        asked = self._asked(unit, code)
        if direction is None:
            if asked is not None:
                direction = "response"
            else:
                kind = describe_pdu(framing, adu, unit, pdu, ok, verdict).kind
                direction = "response" if kind in ("response", "exception") else "request"
        flags = [] if ok else ["bad-checksum"]
        details: dict = {}
        if direction == "response":
            if asked is None:
                flags.append("unsolicited")  # no request seen for it (or it came before we listened)
            else:
                if asked is self._late:
                    flags.append("late")
                latency = max(start - asked.end, 0.0) if self.timed else None
                details = {"latency": latency, "request": asked.number}
                self._pending = self._late = None
            described = describe_pdu(
                framing, adu, unit, pdu, ok, verdict, "response", asked.described if asked else None
            )
        else:
            described = describe_pdu(framing, adu, unit, pdu, ok, verdict, "request")
            if self._pending is not None:
                out.append(self._unanswered(start, self._pending, followed=True))
            self._pending = self._late = None
        if described.kind == "exception":
            flags.append("exception")
        if described.error:
            flags.append("invalid")
        frame = self._frame(
            start,
            end,
            wire,
            direction,
            unit=unit,
            function=code if pdu else None,
            checksum_ok=ok,
            checksum=verdict,
            described=described,
            flags=tuple(flags) + (("broadcast",) if direction == "request" and unit == 0 else ()),
            **details,
        )
        if direction == "request" and ok and unit != 0:
            # A slave answers neither a broadcast nor a frame with a bad checksum (spec §2).
            self._pending = frame
        self._search.reset()  # readings depend on the request waiting: judge afresh
        return out + [frame]
