"""The transaction layer: the client owns time (design notes, "The client owns time").

One ``execute`` is one Modbus transaction: wait out the inter-frame silence and any
--pause, send, then read until the reply arrives or the deadline passes, and retry.  What
the bytes that come back are (the reply, a half-duplex adapter's echo, a reply for someone
else, garbage, the most telling problem seen, so a user learns "CRC error" rather than only
"timeout") is judged by the sans-IO ``codec.exchange.Exchange``; the client keeps the
clocks, the link and the retries.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from mbtool.codec.errors import FrameError, ModbusException
from mbtool.codec.exchange import UNWATCHED, Exchange, Trace, worse
from mbtool.codec.framer import Framer
from mbtool.codec.pdu import ExceptionCode, ExceptionResponse, Request, Response
from mbtool.codec.timing import CHAR_BITS, char_time, silent_interval
from mbtool.errors import NoResponse
from mbtool.link.transport import ConnectionClosed, Transport

# After a complete frame with a bad checksum, how long to wait for a good one
# before calling the reply corrupt (it is nearly always the reply itself).
SETTLE_AFTER_BAD_FRAME = 0.1
# How long a pause ends an RTU frame whose length the codec cannot know
# (an unknown function code, e.g. from `raw`).  USB adapters deliver in bursts.
UNKNOWN_LENGTH_GAP = 0.05
# Work done while a reply is on its way (polling writes the poll before) shorter than this leaves the reply timed from its request, without asking the link
# whether it came meanwhile: its round trip is then long by that much at most, never short.
UNSEEN_WORK = 0.0001


class Client:
    def __init__(
        self,
        transport: Transport,
        framer: Framer,
        *,
        timeout: float = 1.0,
        retries: int = 0,
        echo: bool = False,
        baud: int = 19200,
        char_bits: int = CHAR_BITS,
        trace: Trace | None = None,
        pause: float = 0.0,
        lenient: bool = False,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.transport = transport
        self.framer = framer
        # What the link and the framing are never changes: settled once, not asked a transaction.
        self._serial_line = transport.serial_line  # a serial line keeps t3.5 silences
        self._datagrams = transport.datagrams  # each read a whole datagram (UDP)
        self._broadcast_unit = framer.broadcast_unit
        self._pauses_end_frames = framer.pauses_end_frames  # RTU: a pause may end a frame
        # What may explain silence on this link, until a reply shows its framing right.
        self._silence_hint = transport.silence_hint
        self.timeout = timeout
        self.retries = retries
        # What came back judged, sans-IO: ids, the echo (only a serial line has one to watch
        # for), --lenient's repairs and the most telling problem.
        self.exchange = Exchange(
            framer, echo=echo, watch_echo=transport.serial_line, lenient=lenient, trace=trace
        )
        self.deviations = self.exchange.deviations  # what --lenient let through, each kind once
        self.clock = clock
        self.sleep = sleep
        self._sent_at = 0.0  # when the last request left: what its round trip runs from
        self.attempts = 0  # the requests the last execute sent: 1, or more when it retried
        self._line_free_at = 0.0  # when the last frame on the line ended
        # Run once, right after the next request has left: polling stamps the poll's time
        # there, and writes the previous poll's output while the device turns it round.
        self.while_waiting: Callable[[], None] | None = None
        # When the request that last ran that work left (the clock's time): polling times a
        # poll of several requests from there to the last reply.
        self.work_sent_at = 0.0
        self.replied_at = 0.0  # when the read that brought the last reply's last byte returned
        # The last execute's round trip: seconds from its request's last byte written to its
        # reply's last byte read, what link.stats counts.  None when no reply came, and when
        # its arrival is not known: it came while mbtool was busy after sending (the output
        # blocked on a slow pipe), or after a retry over a link whose frames carry no
        # transaction id (the first request's, late, or the second's?).  Such a reply is
        # left out of the figures rather than timed from the end of that work, which would
        # make it the time it sat in the buffer, shorter than the device can answer.
        self.rtt: float | None = None
        self._settled = False  # the last transaction ended with its reply: nothing stale left
        # The line's own character (10 bits for 8N1): its t3.5 is what the next frame waits.
        self._char_time = char_time(baud, char_bits)
        self._t35 = silent_interval(baud, char_bits)
        # --pause: at least this long from the end of a transaction (its reply, or the wait
        # for one) to the next request, for devices and gateways that drop requests sent
        # back to back.  ``ended_at`` is on the client's clock; polling hands it to the client of
        # a new link to the same device (--reconnect-each, a lost link), which must wait too.
        self.pause = pause
        self.ended_at = float("-inf")

    @property
    def trace(self) -> Trace:
        """Where the frames are reported (--hex); a command may wrap it after opening."""
        return self.exchange.trace

    @trace.setter
    def trace(self, trace: Trace) -> None:
        self.exchange.trace = trace

    def execute(self, unit: int, request: Request) -> Response | None:
        """Send the request and return the reply; None for broadcast or a request with no reply.

        Raises ModbusException for an exception reply, NoResponse, FrameError or
        ConnectionFailed otherwise.
        """
        error: Exception | None = None  # the most telling failure of the attempts
        # The attempts that ended without their reply, (transaction id, when it left): a reply
        # after a retry may be one of theirs, late.
        unanswered: list[tuple[int, float]] | None = None
        self.rtt = None
        # This attempt: the first, then each retry.  (A broadcast ends with its first: nothing
        # can fail after the write, as nothing is waited for.)
        attempt = 1
        while True:
            self.attempts = attempt
            try:
                try:
                    reply = self._transact(unit, request, attempt > 1)
                finally:
                    if self.pause:
                        self.ended_at = self.clock()
            except ConnectionClosed:
                raise  # the link is gone: a retry would only fail to write (exit 6), hiding why
            except (NoResponse, FrameError) as failure:
                self._settled = False  # a late reply may be on its way
                # Its reply may still come, late, after the next attempt has left.
                if unanswered is None:
                    unanswered = []
                unanswered.append((self.exchange.transaction_id, self._sent_at))
                # Bytes that came (a CRC error, a wrong reply) tell more than a later silence.
                error = worse(error, failure)
                if attempt > self.retries:
                    break
                attempt += 1
                continue
            if reply is None:  # broadcast, or a request with no reply: nothing came to settle
                self._settled = False
                return None
            self._settled = True  # the transaction ended with its reply: nothing stale left
            if unanswered is not None:
                self._time_from_attempt_answered(unanswered)
            if self._silence_hint:
                # A reply came over this link, so its framing is right: silence from here on
                # is the device's (it stopped answering), not the mix-up the hint suggests.
                self._silence_hint = self.transport.silence_hint = ""
            if isinstance(reply, ExceptionResponse):
                refusal = ModbusException(reply.function_code, reply.exception_code)
                busy = reply.exception_code == ExceptionCode.SERVER_DEVICE_BUSY
                if not busy or attempt > self.retries:
                    raise refusal
                error = worse(error, refusal)
                attempt += 1
                # Spec §3, exception 06: the device is busy, retry later: the next attempt goes
                # when this one's timeout would have ended, as after silence.
                self.sleep(max(0.0, self._sent_at + self.timeout - self.clock()))
                continue
            return reply
        assert error is not None  # the loop ends only after a failure, which it keeps
        raise error

    # -- one attempt ------------------------------------------------------------

    def _transact(self, unit: int, request: Request, retry: bool) -> Response | ExceptionResponse | None:
        """One attempt: the line's silence and --pause kept, the request sent, and its reply read
        until the deadline; None when no reply is to come (broadcast, FC08 sub 04)."""
        exchange, transport, clock = self.exchange, self.transport, self.clock
        serial_line = self._serial_line
        if serial_line:
            self._wait_for_silence()
        if self.pause:
            wait = self.ended_at + self.pause - clock()
            if wait > 0:
                self.sleep(wait)
        # Over MBAP a stale reply is told by its transaction id, so after a clean transaction
        # a polling loop spares itself the look (a system call a poll) and keeps what the
        # framer holds after the reply; a serial line has no ids, and after a timeout a late
        # reply may be on its way anyway.
        fresh = serial_line or not self._settled
        if fresh:
            stale = transport.discard_input()
            if stale:
                exchange.trace.rejected(
                    stale, FrameError(f"{len(stale)} stale bytes discarded before sending", stale)
                )
        adu = exchange.attempt(unit, request, fresh, retry)
        if exchange.trace is not UNWATCHED:
            # Traced before it goes: a trace that blocks (--hex on a slow terminal) delays the
            # request, not the look for its reply, and is no part of the round trip.
            exchange.trace.sent(adu)
        # The round trip runs from the request's last byte written, never from later: a stamp
        # taken after the write returns is late when the process is preempted there (a busy
        # machine), and the round trip short.  A socket takes the whole frame within the call,
        # so the call's start is as near as the clock can tell and never later (the round trip
        # is long by the call's microseconds at most).
        sent_at = clock()
        transport.write(adu)
        if serial_line:  # the line is busy while the request is on it
            written = clock()
            on_wire = len(adu) * self._char_time
            self._line_free_at = written + on_wire
            # A UART's flush returns when the last byte has left: then, or if it returned late,
            # no sooner than the frame takes on the line from the write's start.
            if written < sent_at + on_wire:
                sent_at = written
            else:
                sent_at += on_wire
        # When the reply's round trip runs from: its request, unless it is not known (inf).
        timed_from = sent_at
        self._sent_at = sent_at
        work = self.while_waiting
        if work is None:
            now = clock()
        else:
            # mbtool's own work while the reply is on its way (the poll before shown), which
            # may block on a slow pipe.
            self.while_waiting = None
            self.work_sent_at = sent_at
            work()
            now = clock()
            # A reply that came meanwhile waited for mbtool, not mbtool for it: when its last
            # byte came is not known, so neither is its round trip.  Asked only when the work
            # took long enough to matter (a reply in a shorter one is timed from its request,
            # at most that much long).
            if now - sent_at > UNSEEN_WORK and transport.input_waiting():
                timed_from = math.inf
        # The timeout runs from now (the write, or the end of that work: mbtool's time, not the
        # device's), or from the request's end on a serial line if that is later.
        deadline = now + self.timeout
        if serial_line and self._line_free_at > now:
            deadline = self._line_free_at + self.timeout
        if not exchange.expects_response and unit == self._broadcast_unit:
            return None  # no device answers a broadcast

        # The reply: read until the exchange finds it, or the deadline passes.  (The framer is
        # asked from self: a poll's reply nearly always comes in the loop's first pass.)
        reply = None
        while now < deadline:
            # RTU, a frame of unknown length: a pause ends it
            waiting = self._pauses_end_frames and self.framer.waiting_for_silence
            try:
                data = transport.read(min(deadline - now, UNKNOWN_LENGTH_GAP) if waiting else deadline - now)
            except ConnectionClosed as closed:  # the peer hung up: judge what it sent before that
                reply = exchange.close(hung_up=True)
                if reply is not None:
                    break
                if exchange.problem is not None:
                    raise ConnectionClosed(f"{closed}; what it sent before: {exchange.problem}") from None
                raise
            if data:
                # The reply's last byte, if these bytes end it, was read now.
                self.replied_at = clock()
                if serial_line:  # the line is busy until now: the next frame waits t3.5 from here
                    self._line_free_at = self.replied_at
                # A datagram (UDP) is whole: its end ends the frame, as silence does on a line.
                reply = exchange.receive(data, self._datagrams)
            else:
                reply = exchange.receive(data, waiting)  # a pause: it ends a frame waiting for one
            if reply is not None:
                break
            now = clock()  # after the judging, which a flood of garbage makes long
            if exchange.settling:
                deadline = min(deadline, now + SETTLE_AFTER_BAD_FRAME)
        if reply is None:
            reply = exchange.close()
        if reply is None:
            # Nothing answered: the most telling problem that came, else silence -- which is
            # what a request without a reply asked for (FC08 sub 04: a device that does not
            # support it refuses it with an exception, which is why it was waited for).
            if exchange.problem is not None:
                raise exchange.problem
            if not exchange.expects_response:
                return None
            raise NoResponse(f"no response from unit {unit} within {self.timeout:g} s{self._silence_hint}")
        # (A reply found without a read of its own is not timed either: replied_at is older.)
        replied_at = self.replied_at
        if replied_at > timed_from:
            self.rtt = replied_at - timed_from
        return reply

    def _time_from_attempt_answered(self, unanswered: list[tuple[int, float]]) -> None:
        """A reply after a retry may answer an earlier attempt, late: over MBAP its transaction
        id names the attempt, and its round trip runs from that one's request; without ids
        (RTU, ASCII) a late reply cannot be told from a prompt one to the last request, so its
        round trip is not known."""
        answered = self.exchange.answered_id
        if answered is None:
            self.rtt = None
            return
        for tid, sent_at in unanswered:
            if tid == answered:
                self.rtt = self.replied_at - sent_at
                return

    def _wait_for_silence(self) -> None:
        """A serial line: t3.5 since the last frame ended before the next may start (spec §2)."""
        wait = self._line_free_at + self._t35 - self.clock()
        if wait > 0:
            self.sleep(wait)
