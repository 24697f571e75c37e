"""One transaction's judgement, sans-IO: of the bytes that come back, which frame is the reply.

The client (``link/client.py``) owns time and the link: it waits, writes, reads until a
deadline and retries.  Everything it decides about what came back is here, as the protocol
reads, with no clock and no I/O: the transaction ids of the request's attempts, the watch for
an adapter's echo of the request, the repair of a harmless fault (--lenient), and the most
telling problem seen, raised when nothing better comes.  An exchange is driven with bytes
and the news that the line paused or went quiet, like the framer under it:

    adu = exchange.attempt(unit, request, fresh=True)   # write it (retry=True: again), then:
    reply = exchange.receive(data, ends_frame)           # each read's bytes (b"": a pause);
                                                         # None: read on
    reply = exchange.close()                             # the deadline: the last word;
    raise exchange.problem or <silence>                  # None: nothing came that tells more
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from mbtool.codec.errors import ChecksumError, FrameError, MismatchError, ModbusException, function_code_text
from mbtool.codec.framer import Frame, Framer, Prediction, Rejected
from mbtool.codec.pdu import ExceptionResponse, Request, Response, pdu_length

Problem = TypeVar("Problem", bound=Exception)

ECHO_SKIPPED = "the request's own echo, skipped (--echo strips it)"


class Trace:
    """Where the frames sent and received are reported (the --hex trace)."""

    def sent(self, adu: bytes) -> None:
        """A frame went out."""

    def received(self, adu: bytes, note: str = "") -> None:
        """A frame came in; ``note`` says why it is not the reply, if it is not."""

    def rejected(self, data: bytes, error: FrameError) -> None:
        """Bytes came in that are not a frame."""


# The trace nobody watches: a transaction's own frames skip the calls to it.
UNWATCHED = Trace()


class Prepared:
    """What is the same for every attempt of one request to one unit, worked out once (and
    never changed): a polling loop sends the same request again and again.  Slots, not a named
    tuple: a tuple's fields are descriptors, which the interpreter reads the generic way, some
    hundred instructions each, and an attempt and its reply read seven of them."""

    __slots__ = (
        "request",
        "unit",
        "expects_response",
        "frame",
        "watched",
        "prediction",
        "reply_size",
        "pdu_at",
        "decode_predicted",
    )

    def __init__(
        self,
        request: Request,
        unit: int,
        expects_response: bool,
        frame: Callable[[int], bytes],
        watched: bool,
        prediction: Prediction | None,
        reply_size: int,
        pdu_at: int,
        decode_predicted: Callable[[bytes], Response | ExceptionResponse],
    ) -> None:
        self.request = request
        self.unit = unit
        self.expects_response = expects_response  # a reply is awaited: not a broadcast, and not FC08 sub 04
        self.frame = frame  # its frame for an attempt's transaction id (Framer.frames)
        self.watched = watched  # an echo of it is watched for
        self.prediction = prediction  # its reply as asked, known beforehand (never when watched)
        self.reply_size = reply_size  # the prediction's size (-1: none), and where its PDU starts
        self.pdu_at = pdu_at
        self.decode_predicted = decode_predicted  # such a reply decoded


def _nothing_predicted(adu: bytes) -> Response | ExceptionResponse:
    raise AssertionError("no reply is predicted")


# Before the first attempt: no request is this one (no unit is -1).
NOTHING_PREPARED = Prepared(
    None,  # type: ignore[arg-type]  # no request, where one is typed: no attempt reads it
    -1,
    True,
    lambda transaction_id: b"",
    False,
    None,
    -1,
    0,
    _nothing_predicted,
)

# The requests an exchange keeps worked out (Prepared), at most: a map's requests take turns on a
# link, a plant's devices' too; past this many it starts again.
KNOWN_REQUESTS = 256


class Exchange:
    """A master's side of its transactions with the devices behind one framer.

    ``echo`` (--echo): the adapter echoes what it sends, always stripped; ``watch_echo``: the
    link is a serial line, where an echo the option does not announce is looked for too.
    ``lenient`` (--lenient): a reply that carries our transaction id and breaks the spec in a
    harmless, unambiguous way is taken, each kind of deviation noted in ``deviations``.
    """

    def __init__(
        self,
        framer: Framer,
        *,
        echo: bool = False,
        watch_echo: bool = False,
        lenient: bool = False,
        trace: Trace | None = None,
    ) -> None:
        self.framer = framer
        self.echo = echo
        self.watch_echo = watch_echo
        self.lenient = lenient
        self.trace = trace or UNWATCHED
        self.transaction_id = 0  # the last attempt's (MBAP; the other framings ignore it)
        # The transaction ids the request went out with, one an attempt: a late reply to an
        # earlier attempt answers the request as well as the last one's would (issue 12.2).
        self.attempt_ids: list[int] = []
        self.answered_id: int | None = None  # the transaction id of the last reply (MBAP)
        self.deviations: dict[str, None] = {}  # each kind once: a poll left running keeps no list
        # The most telling problem of this attempt so far: what is raised if no reply comes.
        self.problem: FrameError | None = None
        # A reply is awaited: the request is not a broadcast, and has one (not FC08 sub 04).
        self.expects_response = True
        self._prepared = NOTHING_PREPARED  # the last request's, to the last unit
        self._known: dict[tuple[int, int], Prepared] = {}  # by the request's id and the unit
        # Bytes that differ from the request are the reply, shown as such (a watched request's).
        self._watch: EchoWatch | None = None
        # The reply if it answers as asked (MBAP): its first bytes, for the first read after
        # the request only; its size and where its PDU starts are the prediction's.
        self._expected: bytes | None = None
        # The framer may hold bytes: it was handed some since it was last found empty (a reply
        # taken as predicted never reaches it).
        self._held = False
        # The last reply to the prepared request decoded: its PDU and what it decoded to.  A poll
        # whose reply is the same bytes gets the same (immutable) response, decoded once.
        self._reply_pdu: bytes | None = None
        self._reply: Response | ExceptionResponse | None = None

    # -- sending -----------------------------------------------------------------------

    def attempt(self, unit: int, request: Request, fresh: bool, retry: bool = False) -> bytes:
        """The next attempt's frame, under a transaction id of its own.  ``fresh``: the link's
        stale input was discarded, so the framer forgets what it holds too.  ``retry``: the
        request again, whose earlier attempts' ids still answer it; else a new request, and the
        last one's ids answer nothing."""
        tid = self.transaction_id = (self.transaction_id + 1) & 0xFFFF
        if retry:
            self.attempt_ids.append(tid)
        else:
            self.attempt_ids = [tid]
        prepared = self._prepared
        if request is not prepared.request or unit != prepared.unit:
            prepared = self._prepare(unit, request)
        frame = prepared.frame  # (a callable kept, read as an attribute: a method's lookup is not)
        adu = frame(tid)
        if fresh:
            self.framer.reset()
            self._held = False
        elif self._held:
            self._held = self.framer.buffered > 0
        prediction = prepared.prediction
        # Bytes the framer still holds come before the reply: then it is not predicted.
        if prediction is None or self._held:
            self._expected = None
        else:
            self._expected = adu[: prediction.repeated] + prediction.head
        self.problem = None
        if prepared.watched:  # (else the watch is None from _prepare on)
            self._watch = EchoWatch(adu)
        return adu

    def _prepare(self, unit: int, request: Request) -> Prepared:
        """Another request, or another unit, than the last attempt's: what every attempt of it
        shares, worked out the first time it is sent."""
        key = (id(request), unit)
        prepared = self._known.get(key)
        if prepared is None or prepared.request is not request:  # (an id outlives its object)
            if len(self._known) >= KNOWN_REQUESTS:
                self._known.clear()
            prepared = self._known[key] = self._worked_out(unit, request)
        self._prepared = prepared
        framer = self.framer
        framer.expect = request
        framer.expect_unit = unit
        self.expects_response = prepared.expects_response
        self._reply_pdu = self._reply = None
        self._watch = None
        return prepared

    def _worked_out(self, unit: int, request: Request) -> Prepared:
        """What every attempt of ``request`` to ``unit`` shares: its frame but the transaction
        id, whether an echo of it is watched for, and its reply as far as it is known before."""
        framer = self.framer
        expects_response = request.expects_response
        awaited = expects_response and unit != framer.broadcast_unit
        # The request's own bytes coming back first are an adapter's echo: with --echo always
        # (even where the reply is a copy of the request, FC05/06), else where an echo cannot
        # pass for the reply.  Only a serial line has an echo to watch for (a map's requests
        # over TCP would pay for the look on every one), and a request with no reply waits only
        # for a refusal, which no echo is mistaken for.
        watched = expects_response and self.watch_echo and (self.echo or EchoWatch.needed(request))
        # An echo, watched for, would come before the reply: then none is predicted.
        prediction = None if watched else framer.predict(unit, request.reply_prefix)
        frame = framer.frames(unit, request.encode())
        if prediction is None:
            return Prepared(request, unit, awaited, frame, watched, None, -1, 0, _nothing_predicted)
        size, pdu_at = prediction.size, prediction.pdu_at
        decode = request.predicted_decoder(pdu_at)
        return Prepared(request, unit, awaited, frame, False, prediction, size, pdu_at, decode)

    # -- receiving ---------------------------------------------------------------------

    @property
    def settling(self) -> bool:
        """A complete frame with a bad checksum came and nothing follows it: nearly always the
        reply itself, so a good one is waited for only a little longer."""
        return isinstance(self.problem, ChecksumError) and not self.framer.buffered

    def receive(self, data: bytes, ends_frame: bool = False) -> Response | ExceptionResponse | None:
        """A read's bytes, or b"" for a read that returned nothing (a pause): the reply if they
        complete it, else None.  ``ends_frame``: the frame ends there, as a whole datagram
        (UDP) ends, or a pause as long as the framer waits for (RTU, a frame of unknown
        length).  The framer's events are judged until the reply, with no look for more.

        Raises FrameError for a reply that is ours (our transaction id) and bad."""
        head = self._expected
        if head is not None:
            # The first read after the request, which nearly always brings exactly the reply
            # predicted: from the unit asked, with our transaction id, the function asked and
            # the byte count for what was asked.  It is taken as it is, unparsed and unjudged.
            self._expected = None
            prepared = self._prepared
            if len(data) == prepared.reply_size and data.startswith(head):
                pdu = data[prepared.pdu_at :]
                if pdu == self._reply_pdu:
                    reply = self._reply  # the same bytes as last time: the same (immutable) response
                else:
                    decode = prepared.decode_predicted  # (an attribute, as frame in attempt)
                    reply = self._reply = decode(data)
                    self._reply_pdu = pdu
                assert reply is not None
                if self.trace is not UNWATCHED:
                    self.trace.received(data)
                self.answered_id = self.transaction_id
                return reply
        self._held = True  # the framer is handed bytes, and may keep some after the reply
        framer, watch = self.framer, self._watch
        if watch is not None:
            if data:
                data = watch.filter(data)
                if watch.seen:
                    self.trace.received(watch.adu, ECHO_SKIPPED)
                    watch.seen = False  # traced once; echoed stays True
            else:
                self._release()  # a pause: bytes held as a possible echo were not one
        if data:
            framer.feed(data)
        event = framer.silence() if ends_frame else framer.next_event()
        while event is not None:
            reply = self._judge(event)
            if reply is not None:
                return reply
            event = framer.next_event()
        return None

    def close(self, hung_up: bool = False) -> Response | ExceptionResponse | None:
        """Nothing more will come (the deadline passed, or the peer hung up: ``hung_up``):
        judge what is still held.  The reply, or None, and then ``problem`` is the most telling
        problem seen (None: only silence)."""
        self._release()
        watch = self._watch
        if not hung_up and watch is not None and watch.echoed and self.problem is None and not self.echo:
            # Bytes came back, but only the request's: an echo, or a device parroting a request
            # it cannot answer.  Either way an invalid response, not silence.
            self.problem = FrameError(
                "the only reply was a copy of the request (an echoing adapter? try --echo)"
            )
        return self.receive(b"", ends_frame=True)

    def _release(self) -> None:
        """Hand the framer the bytes the watch held back as a possible echo: they were not one."""
        if self._watch is not None:
            self.framer.feed(self._watch.release())

    def _judge(self, event: Frame | Rejected) -> Response | ExceptionResponse | None:
        """Is this event our reply?  Otherwise keep the most telling problem seen so far."""
        if isinstance(event, Rejected):
            self.trace.rejected(event.data, event.error)
            self.problem = worse(self.problem, event.error)
            return None
        unit, request = self._prepared.unit, self._prepared.request  # judged only after attempt()
        # What this reply gets away with (--lenient), for its trace line: a tuple, as the empty
        # one is made once, not a list a reply.
        accepted: tuple[str, ...] = ()
        mismatch = self._mismatch(event, unit)
        if mismatch:
            if event.unit != unit and self._ours(event) and not self._mismatch(event, event.unit):
                # Our transaction id, the function asked for, only the unit is wrong: a gateway
                # that echoes another unit id.
                if not self.lenient:
                    mismatch += " (--lenient accepts a reply whose transaction id matches)"
                else:
                    accepted += (f"reply from unit {event.unit}, expected unit {unit}",)
                    mismatch = ""
            if mismatch:
                self.trace.received(event.adu, mismatch)
                self.problem = worse(self.problem, MismatchError(mismatch + ", discarded", event.adu))
                return None
        # From the unit asked, to the function asked: the reply, unless it does not decode.
        pdu = event.pdu
        reply = self._reply
        try:
            if pdu != self._reply_pdu:  # else the same response as last time (immutable)
                reply = self._reply = request.decode_response(pdu)
                self._reply_pdu = pdu
        except FrameError as misfit:
            repaired = repair(pdu, request) if self._ours(event) else None
            if repaired is not None and self.lenient:
                pdu, deviation = repaired
                reply = request.decode_response(pdu)
                accepted += (deviation,)
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
                self.problem = worse(self.problem, MismatchError(f"{misfit}, discarded", event.adu))
                return None
        assert reply is not None
        if accepted:  # a reply taken as it is (--lenient): the summary says so
            self.deviations.update(dict.fromkeys(accepted))
        if self.trace is not UNWATCHED:
            self.trace.received(event.adu, _reply_note(reply, accepted))
        self.answered_id = event.transaction_id
        return reply

    def _ours(self, frame: Frame) -> bool:
        """The frame carries the transaction id of one of this request's attempts (MBAP)."""
        return frame.transaction_id is not None and frame.transaction_id in self.attempt_ids

    def _copy_check(self, frame: Frame) -> None:
        """A reply that does not decode and is the request itself: over TCP nothing echoes but a
        misconfigured server or gateway, and that is the line to read, not the decoder's."""
        if frame.transaction_id is not None and frame.adu == self._prepared.frame(self.transaction_id):
            raise FrameError(
                "the only reply was a copy of the request (the server, or a gateway on the way, echoes requests)",
                frame.adu,
            )

    def _mismatch(self, frame: Frame, unit: int) -> str:
        """Why the frame answers another transaction, or "" when it answers this one."""
        tid = frame.transaction_id
        if tid is not None and tid not in self.attempt_ids:  # not _ours(): a call less a reply
            return f"reply has transaction id {tid}, expected {_ids(self.attempt_ids)}"
        if frame.unit != unit:
            return f"reply from unit {frame.unit}, expected unit {unit}"
        pdu = frame.pdu
        code = pdu[0] if pdu else None
        asked = self._prepared.request.function_code
        if code != asked and code != asked | 0x80:
            shown = "no function code" if code is None else function_code_text(code)
            return f"reply has {shown}, expected {function_code_text(asked)}"
        return ""


def repair(pdu: bytes, request: Request) -> tuple[bytes, str] | None:
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


class EchoWatch:
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


def worse(current: Problem | None, new: Problem) -> Problem:
    """The more telling of two problems: a checksum error or a mismatched reply tells more than
    a run of garbage, and anything that came (a FrameError) tells more than what did not (the
    client's silence) or a refusal; between equals, the first seen."""
    if current is None:
        return new
    for telling in ((ChecksumError, MismatchError), FrameError):
        if isinstance(new, telling) and not isinstance(current, telling):
            return new
        if isinstance(current, telling):
            return current
    return current


def _reply_note(reply: Response | ExceptionResponse, accepted: tuple[str, ...]) -> str:
    """What the trace says beside the reply: why --lenient took it as it is, or the device's
    "no", marked where it is seen; nothing for a plain answer."""
    if accepted:
        return "; ".join(f"accepted (--lenient): {d}" for d in accepted)
    if isinstance(reply, ExceptionResponse):
        return str(ModbusException(reply.function_code, reply.exception_code))
    return ""


def _ids(ids: list[int]) -> str:
    return str(ids[0]) if len(ids) == 1 else ", ".join(map(str, ids[:-1])) + f" or {ids[-1]}"
