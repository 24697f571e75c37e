"""The transaction layer: the client owns time (design notes, "The client owns time").

One ``execute`` is one Modbus transaction: wait out the inter-frame silence,
send, strip a half-duplex adapter's echo, then read until a reply that answers
this request arrives or the deadline passes.  Replies for someone else (another
unit, another function, a stale transaction id) are discarded; garbage is
skipped.  When the deadline passes, the most telling problem seen is raised,
so a user learns "CRC error" rather than only "timeout".
"""

from __future__ import annotations

import time
from collections.abc import Callable

from mbtool.codec.errors import ChecksumError, FrameError, MismatchError, ModbusException, function_code_text
from mbtool.codec.framer import Frame, Framer, Rejected
from mbtool.codec.pdu import ExceptionCode, ExceptionResponse, Request, Response, pdu_length
from mbtool.codec.timing import CHAR_BITS, char_time, silent_interval
from mbtool.errors import MbtoolError, NoResponse
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


class Trace:
    """Where the client reports the frames it sends and receives (the --hex trace)."""

    def sent(self, adu: bytes) -> None:
        """A frame went out."""

    def received(self, adu: bytes, note: str = "") -> None:
        """A frame came in; ``note`` says why it is not the reply, if it is not."""

    def rejected(self, data: bytes, error: FrameError) -> None:
        """Bytes came in that are not a frame."""


# The trace of a client nobody watches: a transaction's own frames skip the calls to it.
UNWATCHED = Trace()


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
        self.timeout = timeout
        self.retries = retries
        self.echo = echo  # the adapter echoes what it sends (half-duplex RS-485)
        self.trace = trace or UNWATCHED
        self.clock = clock
        self.sleep = sleep
        self._transaction_id = 0
        self._sent = b""  # the last request's frame, to tell a copy of it from a reply
        self._sent_at = 0.0  # when it left: what its round trip runs from
        # The transaction ids this request went out with, one an attempt: a late reply to an
        # earlier attempt answers the request as well as the last one's would (issue 12.2).
        self._attempt_ids: list[int] = []
        self._answered_id: int | None = None  # the transaction id of the last reply (MBAP)
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
        # The last request, its PDU, whether its echo could pass for a reply, whether it has
        # one and what is known of it beforehand: the same for every poll of it, so worked
        # out once.
        self._prepared: tuple[Request | None, bytes, bool, bool, tuple[bytes, int] | None] = (
            None,
            b"",
            False,
            True,
            None,
        )
        # The last reply decoded: the request, the reply's PDU and what it decoded to.  A poll
        # whose reply is the same bytes gets the same (immutable) response, decoded once.
        self._decoded: tuple[Request | None, bytes, Response | ExceptionResponse | None] = (None, b"", None)
        # The line's own character (10 bits for 8N1): its t3.5 is what the next frame waits.
        self._char_time = char_time(baud, char_bits)
        self._t35 = silent_interval(baud, char_bits)
        # --pause: at least this long from the end of a transaction (its reply, or the wait
        # for one) to the next request, for devices and gateways that drop requests sent
        # back to back.  ``ended_at`` is on the client's clock; polling hands it to the client of
        # a new link to the same device (--reconnect-each, a lost link), which must wait too.
        self.pause = pause
        self.ended_at = float("-inf")
        # --lenient: a Modbus TCP reply that carries our transaction id and breaks the spec
        # in a harmless, unambiguous way is accepted, and each deviation noted here.
        self.lenient = lenient
        self.deviations: dict[str, None] = {}  # each kind once: a poll left running keeps no list

    def execute(self, unit: int, request: Request) -> Response | None:
        """Send the request and return the reply; None for broadcast or a request with no reply.

        Raises ModbusException for an exception reply, NoResponse, FrameError or
        ConnectionFailed otherwise.
        """
        attempts = 1 if unit == self.framer.broadcast_unit else self.retries + 1
        error: MbtoolError | None = None
        self._attempt_ids.clear()
        # The attempts that ended without their reply, (transaction id, when it left): a reply
        # after a retry may be one of theirs, late.
        unanswered: list[tuple[int, float]] | None = None
        self.rtt = None
        busy = False
        for attempt in range(attempts):
            self.attempts = attempt + 1
            if busy:
                # Spec §3, exception 06: the device is busy, retry later: the next attempt goes
                # when this one's timeout would have ended, as after silence.
                self.sleep(max(0.0, self._sent_at + self.timeout - self.clock()))
            try:
                try:
                    reply = self._transact(unit, request)
                finally:
                    if self.pause:
                        self.ended_at = self.clock()
                self._settled = reply is not None
                if unanswered is not None and reply is not None:
                    self._time_from_attempt_answered(unanswered)
            except ConnectionClosed:
                raise  # the link is gone: a retry would only fail to write (exit 6), hiding why
            except (NoResponse, FrameError) as failure:
                # Its reply may still come, late, after the next attempt has left.
                if unanswered is None:
                    unanswered = []
                unanswered.append((self._transaction_id, self._sent_at))
                # Bytes that came (a CRC error, a wrong reply) tell more than a later silence.
                error = _worse(error, failure)
                busy = False
                continue
            if reply is not None and self.transport.silence_hint:
                # A reply came over this link, so its framing is right: silence from here on
                # is the device's (it stopped answering), not the mix-up the hint suggests.
                self.transport.silence_hint = ""
            if isinstance(reply, ExceptionResponse):
                refusal = ModbusException(reply.function_code, reply.exception_code)
                busy = reply.exception_code == ExceptionCode.SERVER_DEVICE_BUSY
                if not busy or attempt + 1 == attempts:
                    raise refusal
                error = _worse(error, refusal)
                continue
            return reply
        assert error is not None
        raise error

    # -- one attempt ------------------------------------------------------------

    def _transact(self, unit: int, request: Request) -> Response | ExceptionResponse | None:
        framer, transport = self.framer, self.transport
        tid = self._transaction_id = (self._transaction_id + 1) & 0xFFFF
        self._attempt_ids.append(tid)
        if request is not self._prepared[0]:
            self._prepared = (
                request,
                request.encode(),
                # Only a serial line has an echo to watch for (a map's requests over TCP
                # would pay for the look on every one).
                transport.serial_line and _EchoWatch.needed(request),
                request.expects_response,
                request.reply_prefix,
            )
        _, pdu, echo_watched, expects_response, reply_prefix = self._prepared
        adu = framer.build(unit, pdu, tid)
        serial_line = transport.serial_line
        if serial_line:
            self._wait_for_silence()
        if self.pause:
            wait = self.ended_at + self.pause - self.clock()
            if wait > 0:
                self.sleep(wait)
        # Over MBAP a stale reply is told by its transaction id, so after a clean transaction
        # a polling loop spares itself the look (a system call a poll) and keeps what the
        # framer holds after the reply; a serial line has no ids, and after a timeout a late
        # reply may be on its way anyway.
        if serial_line or not self._settled:
            stale = transport.discard_input()
            if stale:
                self.trace.rejected(
                    stale, FrameError(f"{len(stale)} stale bytes discarded before sending", stale)
                )
            framer.reset()
        self._settled = False  # until this attempt ends with its reply
        framer.expect = request
        framer.expect_unit = unit
        framer.predict(unit, tid, reply_prefix)
        if self.trace is not UNWATCHED:
            # Traced before it goes: a trace that blocks (--hex on a slow terminal) delays the
            # request, not the look for its reply, and is no part of the round trip.
            self.trace.sent(adu)
        # The round trip runs from the request's last byte written, never from later: a stamp
        # taken after the write returns is late when the process is preempted there (a busy
        # machine), and the round trip short.  A socket takes the whole frame within the call,
        # so the call's start is as near as the clock can tell and never later (the round trip
        # is long by the call's microseconds at most).
        sent_at = self.clock()
        transport.write(adu)
        written = self.clock()
        deadline = written + self.timeout
        if serial_line:  # the line is busy while the request is on it
            on_wire = len(adu) * self._char_time
            self._line_free_at = written + on_wire
            deadline += on_wire
            # A UART's flush returns when the last byte has left: then, or if it returned late,
            # no sooner than the frame takes on the line from the write's start.
            if written < sent_at + on_wire:
                sent_at = written
            else:
                sent_at += on_wire
        self._sent_at = sent_at
        timed_from: float | None = sent_at
        work = self.while_waiting
        if work is not None:
            # mbtool's own work while the reply is on its way (the poll before shown), which
            # may block on a slow pipe.
            self.while_waiting = None
            self.work_sent_at = sent_at
            work()
            # The timeout runs from here at the earliest: the work was mbtool's time, not the
            # device's.
            done = self.clock()
            if done + self.timeout > deadline:
                deadline = done + self.timeout
            # A reply that came meanwhile waited for mbtool, not mbtool for it: when its last
            # byte came is not known, so neither is its round trip.  Asked only when the work
            # took long enough to matter (a reply in a shorter one is timed from its request,
            # at most that much long).
            if done - sent_at > UNSEEN_WORK and transport.input_waiting():
                timed_from = None
        if unit == framer.broadcast_unit:
            return None
        if not expects_response:
            # No reply is the outcome asked for (FC08 sub 04), but a device that does not
            # support the request still refuses it with an exception: wait for that.
            try:
                return self._await_reply(unit, request, deadline, None)
            except ConnectionClosed:
                raise
            except NoResponse:
                return None
        # The request's own bytes coming back first are an adapter's echo: with --echo always
        # (even where the reply is a copy of the request, FC05/06), else where an echo cannot
        # pass for the reply.  Bytes that differ from the request are the reply, shown as such.
        watch = _EchoWatch(adu) if serial_line and (self.echo or echo_watched) else None
        self._sent = adu
        reply = self._await_reply(unit, request, deadline, watch)
        # (A reply found without a read of its own is not timed either: replied_at is older.)
        replied_at = self.replied_at
        if timed_from is not None and replied_at > timed_from:
            self.rtt = replied_at - timed_from
        return reply

    def _time_from_attempt_answered(self, unanswered: list[tuple[int, float]]) -> None:
        """A reply after a retry may answer an earlier attempt, late: over MBAP its transaction
        id names the attempt, and its round trip runs from that one's request; without ids
        (RTU, ASCII) a late reply cannot be told from a prompt one to the last request, so its
        round trip is not known."""
        answered = self._answered_id
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

    def _await_reply(
        self, unit: int, request: Request, deadline: float, watch: _EchoWatch | None = None
    ) -> Response | ExceptionResponse:
        problem: FrameError | None = None
        framer, transport = self.framer, self.transport
        serial_line = transport.serial_line
        while True:
            now = self.clock()
            if now >= deadline:
                break
            waiting = framer.waiting_for_silence
            try:
                data = transport.read(min(deadline - now, UNKNOWN_LENGTH_GAP) if waiting else deadline - now)
            except ConnectionClosed as closed:  # the peer hung up: judge what it sent before that
                self._release(watch)
                return self._last_word(unit, request, problem, closed, hung_up=True)
            if data:
                # The reply's last byte, if these bytes end it, was read now.
                read_at = self.replied_at = self.clock()
                if serial_line:  # the line is busy until now: the next frame waits t3.5 from here
                    self._line_free_at = read_at
                if watch is not None:
                    data = watch.filter(data)
                    if watch.seen:
                        self.trace.received(watch.adu, "the request's own echo, skipped (--echo strips it)")
                        watch.seen = False  # traced once; echoed stays True
                framer.feed(data)
                # A datagram (UDP) is whole: its end ends the frame, as silence does on a line.
                event = framer.silence() if transport.datagrams else framer.next_event()
            else:
                self._release(watch)  # a pause: bytes held as a possible echo were not one
                event = framer.silence() if waiting else framer.next_event()
            while event is not None:  # judged until the reply, with no look for more
                reply, problem = self._judge(event, unit, request, problem)
                if reply is not None:
                    return reply
                event = framer.next_event()
            if isinstance(problem, ChecksumError) and not framer.buffered:
                deadline = min(deadline, self.clock() + SETTLE_AFTER_BAD_FRAME)
        self._release(watch)
        if watch is not None and watch.echoed and problem is None and not self.echo:
            # Bytes came back, but only the request's: an echo, or a device parroting a request
            # it cannot answer.  Either way an invalid response, not silence.
            problem = FrameError("the only reply was a copy of the request (an echoing adapter? try --echo)")
        return self._last_word(
            unit,
            request,
            problem,
            NoResponse(
                f"no response from unit {unit} within {self.timeout:g} s{self.transport.silence_hint}"
            ),
        )

    def _release(self, watch: _EchoWatch | None) -> None:
        """Hand the framer the bytes the watch held back as a possible echo: they were not one."""
        if watch is not None:
            self.framer.feed(watch.release())

    def _judge_events(
        self, event: Frame | Rejected | None, unit: int, request: Request, problem: FrameError | None
    ) -> tuple[Response | ExceptionResponse | None, FrameError | None]:
        """Judge the framer's events from ``event`` on; judging stops at the reply, with no look for more."""
        while event is not None:
            reply, problem = self._judge(event, unit, request, problem)
            if reply is not None:
                return reply, problem
            event = self.framer.next_event()
        return None, problem

    def _last_word(
        self,
        unit: int,
        request: Request,
        problem: FrameError | None,
        silence: NoResponse,
        hung_up: bool = False,
    ) -> Response | ExceptionResponse:
        """Nothing more will come: judge what is still buffered, then raise the most telling problem.

        When the peer hung up (``hung_up``), that is the error, naming what came before it:
        the link is gone, so no retry can follow, and polling reopens it (exit 3).
        """
        reply, problem = self._judge_events(self.framer.silence(), unit, request, problem)
        if reply is not None:
            return reply
        if hung_up and problem is not None:
            raise ConnectionClosed(f"{silence}; what it sent before: {problem}")
        raise problem or silence

    def _judge(
        self, event: Frame | Rejected, unit: int, request: Request, problem: FrameError | None
    ) -> tuple[Response | ExceptionResponse | None, FrameError | None]:
        """Is this event our reply?  Otherwise keep the most telling problem seen so far."""
        if isinstance(event, Rejected):
            self.trace.rejected(event.data, event.error)
            return None, _worse(problem, event.error)
        accepted: list[str] = []  # what this reply gets away with (--lenient), for its trace line
        # The frame the MBAP framer built from its prediction has the unit, function,
        # transaction id and byte count asked for: nothing to look at again.
        mismatch = "" if event is self.framer.predicted_frame else self._mismatch(event, unit, request)
        if mismatch:
            if event.unit != unit and self._ours(event) and not self._mismatch(event, event.unit, request):
                # Our transaction id, the function asked for, only the unit is wrong: a gateway
                # that echoes another unit id.
                if not self.lenient:
                    mismatch += " (--lenient accepts a reply whose transaction id matches)"
                else:
                    accepted.append(f"reply from unit {event.unit}, expected unit {unit}")
                    mismatch = ""
            if mismatch:
                self.trace.received(event.adu, mismatch)
                return None, _worse(problem, MismatchError(mismatch + ", discarded", event.adu))
        # From the unit asked, to the function asked: the reply, unless it does not decode.
        pdu = event.pdu
        last_request, last_pdu, reply = self._decoded
        try:
            if request is not last_request or pdu != last_pdu:
                # The same response as last time for the same request and bytes (immutable).
                reply = request.decode_response(pdu)
                self._decoded = (request, pdu, reply)
        except FrameError as misfit:
            repaired = self._repair(pdu, request) if self._ours(event) else None
            if repaired is not None and self.lenient:
                pdu, deviation = repaired
                reply = request.decode_response(pdu)
                accepted.append(deviation)
            elif event.transaction_id is not None:
                self.trace.received(event.adu)
                self._copy_check(event)
                if repaired is not None:
                    raise FrameError(f"{misfit} ({repaired[1]}: --lenient accepts it)", event.adu) from None
                raise  # it carries our transaction id: it is the reply, and a bad one
            elif not isinstance(misfit, MismatchError):
                self.trace.received(event.adu)
                self._copy_check(event)
                raise
            else:
                # Without a transaction id (RTU, ASCII), a frame from our unit whose byte
                # count does not fit is most likely the late reply to an earlier request:
                # discard it and keep waiting, as for another unit (its error is reported
                # if nothing fits).
                self.trace.received(event.adu, str(misfit))
                return None, _worse(problem, MismatchError(f"{misfit}, discarded", event.adu))
        if accepted:  # a reply taken as it is (--lenient): the summary says so
            self.deviations.update(dict.fromkeys(accepted))
        if self.trace is not UNWATCHED:
            self.trace.received(event.adu, _reply_note(reply, accepted))
        self._answered_id = event.transaction_id
        return reply, problem

    def _ours(self, frame: Frame) -> bool:
        """The frame carries the transaction id of one of this request's attempts (MBAP)."""
        return frame.transaction_id is not None and frame.transaction_id in self._attempt_ids

    @staticmethod
    def _repair(pdu: bytes, request: Request) -> tuple[bytes, str] | None:
        """A reply PDU made whole, and what was wrong with it, when the fault is harmless and
        unambiguous: bytes after a complete reply (MBAP counted them), or a byte count that
        disagrees with data that is exactly what was asked for.  None otherwise."""
        if pdu and pdu[0] & 0x80:
            return None
        whole = pdu_length(pdu, True, request)
        if isinstance(whole, int) and whole >= 2 and len(pdu) > whole:
            try:
                request.decode_response(pdu[:whole])
            except FrameError:
                pass
            else:
                return pdu[:whole], f"{len(pdu) - whole} bytes after a complete reply, ignored"
        wanted = getattr(request, "reply_byte_count", None)  # reads of FC 01-04 know theirs
        if wanted is not None and len(pdu) == 2 + wanted and pdu[1] != wanted:
            whole_pdu = pdu[:1] + bytes([wanted]) + pdu[2:]
            return whole_pdu, f"byte count {pdu[1]}, but the data is the {wanted} bytes asked for"
        return None

    def _copy_check(self, frame: Frame) -> None:
        """A reply that does not decode and is the request itself: over TCP nothing echoes but a
        misconfigured server or gateway, and that is the line to read, not the decoder's."""
        if frame.transaction_id is not None and frame.adu == self._sent:
            raise FrameError(
                "the only reply was a copy of the request (the server, or a gateway on the way, echoes requests)",
                frame.adu,
            )

    def _mismatch(self, frame: Frame, unit: int, request: Request) -> str:
        tid = frame.transaction_id
        if tid is not None and tid not in self._attempt_ids:  # not _ours(): a call less a reply
            return f"reply has transaction id {tid}, expected {_ids(self._attempt_ids)}"
        if frame.unit != unit:
            return f"reply from unit {frame.unit}, expected unit {unit}"
        pdu = frame.pdu
        code = pdu[0] if pdu else None
        asked = request.function_code
        if code != asked and code != asked | 0x80:
            shown = "no function code" if code is None else function_code_text(code)
            return f"reply has {shown}, expected {function_code_text(asked)}"
        return ""


class _EchoWatch:
    """Without --echo: the request's own bytes coming back first are an adapter's echo.

    A half-duplex RS-485 adapter that hears itself puts the request before the reply;
    taken for a reply it reads as a CRC error or a nonsense byte count.  The watch holds
    back bytes while they repeat the request, drops an exact copy of it, and hands back
    anything else untouched.  Requests whose reply may be an exact copy of them (FC05,
    FC06, FC08) are not watched: there an echo and a reply cannot be told apart.
    """

    def __init__(self, adu: bytes) -> None:
        self.adu = adu
        self.held = b""
        self.watching = True
        self.seen = False  # the echo just went by (for the trace)
        self.echoed = False  # the echo went by in this transaction

    @staticmethod
    def needed(request: Request) -> bool:
        """Whether an echo of ``request`` can be told from its reply (it cannot pass for one)."""
        try:
            request.decode_response(request.encode())
        except Exception:  # whatever the reason, the request does not read as its own reply
            return True
        return False

    def filter(self, data: bytes) -> bytes:
        """What of ``data`` the framer should see now."""
        if not self.watching:
            return data
        self.held += data
        size = min(len(self.held), len(self.adu))
        if self.held[:size] != self.adu[:size]:
            return self.release()
        if len(self.held) < len(self.adu):
            return b""  # so far a copy of the request: wait for the rest
        rest = self.held[len(self.adu) :]
        self.held = b""
        self.watching = False
        self.seen = self.echoed = True
        return rest

    def release(self) -> bytes:
        """Stop watching; the bytes held back, which were not an echo after all."""
        held, self.held = self.held, b""
        self.watching = False
        return held


def _reply_note(reply: Response | ExceptionResponse, accepted: list[str]) -> str:
    """What the trace says beside the reply: why --lenient took it as it is, or the device's
    "no", marked where it is seen; nothing for a plain answer."""
    if accepted:
        return "; ".join(f"accepted (--lenient): {d}" for d in accepted)
    if isinstance(reply, ExceptionResponse):
        return str(ModbusException(reply.function_code, reply.exception_code))
    return ""


def _ids(ids: list[int]) -> str:
    return str(ids[0]) if len(ids) == 1 else ", ".join(map(str, ids[:-1])) + f" or {ids[-1]}"


def _worse(current: MbtoolError | None, new: MbtoolError) -> MbtoolError:
    """The more telling of two problems: a checksum error or a mismatched reply tells more than
    a run of garbage, and anything that came tells more than silence (NoResponse); between
    equals, the first seen."""
    if current is None:
        return new
    for telling in ((ChecksumError, MismatchError), FrameError):
        if isinstance(new, telling) and not isinstance(current, telling):
            return new
        if isinstance(current, telling):
            return current
    return current
