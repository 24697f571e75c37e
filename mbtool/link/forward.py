"""The gateway's master side (``mbtool bridge``): other masters' requests forwarded as they are.

Each request's PDU goes to the unit it names through a ``Client``, so the link behind keeps
its t3.5 silences, a half-duplex echo is stripped and the reply is checked like any other;
the reply's PDU goes back unchanged, a device's own exception included.  Where the gateway
must answer for the device it says so with the exceptions the spec keeps for gateways
(spec §3; the Modbus TCP implementation guide, "gateway" exception codes):

* 0B Gateway Target Device Failed to Respond: no reply within the timeout, or none whole
  (a CRC/LRC error, the wrong unit or function).  A unit that sent nothing at all is then
  answered 0B at once, without the bus, for ``silent_hold`` seconds: a master asking again
  and again for a unit that is not there does not cost every other master its timeout.
* 0A Gateway Path Unavailable: the unit is not one this gateway forwards (``--units``), or the
  link behind it cannot be opened or broke.  It is opened again for the next request, so a
  USB adapter plugged back in or a TCP device restarted is used again without a restart.

A request goes on the bus only if the device could take it: each is read as a device reads
it, by the codec's layout of its function code (``codec.pdu.check_request``), and one that
does not fit is answered as the device would, 01 or 03 (02 for an address past 65535),
without the bus.  A function code the codec does not know is forwarded only when asked
(``raw_functions``); 00 and 80-FF are never function codes.

A broadcast (unit 0 where a serial line is either side, spec §2) is forwarded only if unit 0
is among the units, only if it is a write, and is never answered.
Requests come from a device-side framer (``mbtool.device.server``), one at a time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager

from mbtool.codec.errors import FrameError, ModbusException, RequestError
from mbtool.codec.framing import Frame, Framer, Rejected, is_broadcast
from mbtool.codec.pdu import ExceptionCode, ExceptionResponse, check_request
from mbtool.codec.raw import RawRequest
from mbtool.codec.record import record
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link.client import Client, Trace
from mbtool.link.managed import LOST, Backoff, ManagedLink
from mbtool.link.stats import Stats
from mbtool.link.transport import ConnectionClosed

# What became of a request, in the words the display and the summary use.
REPLY = "reply"  # the device's reply, passed on
REFUSED = "exception"  # the device's exception reply, passed on
BROADCAST = "broadcast"  # sent to every unit, answered by none
NO_RESPONSE = "no response"  # answered 0B
NO_PATH = "no path"  # answered 0A (or, on a serial line, a unit left to other slaves)
INVALID = "invalid"  # a request no device could take: answered 01 or 03, never forwarded
OUTCOMES = (REPLY, REFUSED, BROADCAST, NO_RESPONSE, NO_PATH, INVALID)
SILENT_HOLD = 5.0  # seconds a unit that sent nothing is answered 0B without the bus


@record
class Passage:
    """One request through the gateway, as the display shows it."""

    time: float  # when the request arrived, seconds since the epoch
    peer: str  # who sent it: a TCP client's address, or the serial line
    unit: int
    function: int
    request: bytes  # the request as it came (its ADU)
    upstream: str  # its framing: tcp, rtu or ascii
    sent: bytes  # the request as forwarded, b"" if it was not
    downstream: str  # that side's framing
    received: bytes  # the reply as it came back, b"" if none did
    reply: bytes  # the reply as sent back, b"" if none was
    outcome: str  # one of OUTCOMES
    why: str  # what the gateway saw: the device's exception, why 0A or 0B, a garbled reply
    bus_time: float | None  # seconds from the forwarded request leaving to its reply arriving
    total: float  # seconds from the request's arrival to the reply being ready


class _Watch(Trace):
    """The frames of one forwarded transaction, for its Passage."""

    def __init__(self) -> None:
        self.request = b""
        self.reply = b""
        self.problems: list[str] = []  # frames that were not the reply, and why
        self.sent_at = self.received_at = 0.0

    def sent(self, adu: bytes) -> None:
        self.request = adu
        self.sent_at = time.monotonic()

    def received(self, adu: bytes, note: str = "") -> None:
        if note:
            self.problems.append(note)
        else:
            self.reply = adu
            self.received_at = time.monotonic()

    @property
    def bus_time(self) -> float | None:
        return self.received_at - self.sent_at if self.reply else None

    def rejected(self, data: bytes, error: FrameError) -> None:
        self.problems.append(str(error))


class Forwarder:
    """Answers requests by forwarding them over a link opened by ``open_link``.

    ``open_link()`` is a context manager giving an open Client (what
    ``mbtool.link.connection.open_client`` gives).  ``units``: the units forwarded (0: the
    broadcasts).  ``raw_functions``: forward function codes the codec does not know.
    ``silent_hold``: seconds a unit that did not respond is answered 0B at once (0: never).
    Every request ends in a ``Passage`` handed to ``report``; each one forwarded is also a
    transaction on the link, counted in ``stats`` by its unit (``link.stats``).  A request sent
    again on a new link, after the one it went out on had closed, is a second transaction.
    """

    def __init__(
        self,
        open_link: Callable[[], AbstractContextManager[Client]],
        framing: str,
        units: frozenset[int],
        report: Callable[[Passage], None],
        raw_functions: bool = False,
        silent_hold: float = SILENT_HOLD,
    ) -> None:
        self.open_link = open_link
        self.framing = framing  # the link's: rtu, ascii or tcp
        self.units = units
        self.report = report
        self.raw_functions = raw_functions
        self.silent_hold = silent_hold
        self._silent: dict[int, float] = {}  # unit -> when it last sent nothing (monotonic)
        self.stats: dict[int, Stats] = {}  # unit -> its transactions on the link
        # Opened at the first request (or ``open``), and again after it was lost, at once: a
        # request waits for no back-off, and its client is told why its request went nowhere.
        self.link = ManagedLink(open_link, Backoff(0.0))
        self._watch = _Watch()

    def answer(self, event: Frame | Rejected, framer: Framer, peer: str) -> bytes | None:
        """The reply ADU to a request from ``peer``, in the framing it came in; None: none is due.

        What ``mbtool.device.server.Server`` asks of whoever answers its requests
        (``mbtool.device.serving.Answerer``).
        """
        if not isinstance(event, Frame) or not event.pdu:  # bytes that made no request
            return None
        arrived, started = time.time(), time.monotonic()
        unit, function = event.unit, event.pdu[0]
        watch = self._watch = _Watch()
        broadcast = self._broadcast(unit, framer)
        refusal = self._refusal(unit, event.pdu, broadcast)
        if refusal is None:
            pdu, outcome, why = self._forward(unit, event.pdu, broadcast)
        else:
            code, outcome, why = refusal
            # On a serial line nobody answers a broadcast (spec §2), and a unit not ours is
            # another slave's; a TCP client is told why its request went nowhere.
            serial = framer.broadcast_unit is not None
            pdu = None if serial and (broadcast or outcome == NO_PATH) else _exception(function, code)
        reply = b"" if pdu is None else framer.build(unit, pdu, event.transaction_id or 0)
        self.report(
            Passage(
                arrived,
                peer,
                unit,
                function,
                event.adu,
                framer.name,
                watch.request,
                self.framing,
                watch.reply,
                reply,
                outcome,
                why,
                watch.bus_time,
                time.monotonic() - started,
            )
        )
        return reply or None

    def open(self) -> None:
        """Open the link now: ConnectionFailed (exit 6) if it cannot be, before any request."""
        self._open()

    def close(self) -> None:
        self.link.close()

    # -- forwarding --------------------------------------------------------------------

    def _broadcast(self, unit: int, framer: Framer) -> bool:
        """Unit 0 where a serial line is either side: the bus's broadcast (spec §2)."""
        return unit == 0 and (framer.broadcast_unit == 0 or is_broadcast(0, self.framing))

    def _refusal(self, unit: int, pdu: bytes, broadcast: bool) -> tuple[int, str, str] | None:
        """Why the gateway answers a request itself (exception code, outcome, why), or None:
        it goes on the bus."""
        if unit not in self.units:
            return ExceptionCode.GATEWAY_PATH_UNAVAILABLE, NO_PATH, f"unit {unit} is not forwarded (--units)"
        try:
            request = check_request(pdu)
        except RequestError as error:
            unknown = error.exception_code == ExceptionCode.ILLEGAL_FUNCTION
            if not (unknown and self.raw_functions and 0x01 <= pdu[0] <= 0x7F):
                return error.exception_code, INVALID, f"not forwarded: {error}"
            request = None  # a function the codec does not know, forwarded as it is
        if broadcast and (request is None or not request.broadcastable):
            return (
                ExceptionCode.ILLEGAL_FUNCTION,
                INVALID,
                "not forwarded: only writes are broadcast (spec §2)",
            )
        silent = time.monotonic() - self._silent.get(unit, float("-inf"))
        if silent < self.silent_hold:
            why = (
                f"unit {unit} did not respond {silent:.1f} s ago: not tried again for {self.silent_hold:g} s"
            )
            return ExceptionCode.GATEWAY_TARGET_FAILED_TO_RESPOND, NO_RESPONSE, why + " (--silent-hold)"
        return None

    def _forward(self, unit: int, pdu: bytes, broadcast: bool) -> tuple[bytes | None, str, str]:
        """The reply PDU (None: none is due), the outcome and what was seen."""
        answer: bytes | None
        try:
            reply = self._execute(unit, RawRequest(pdu))
        except ModbusException as refusal:
            self._silent.pop(unit, None)
            answer = _exception(refusal.function_code, refusal.exception_code)
            outcome, why = REFUSED, str(refusal)
        except LOST as lost:  # the managed link has closed it: a new one for the next request
            why = (lost.strerror or str(lost)) if isinstance(lost, OSError) else str(lost)
            answer, outcome = _exception(pdu[0], ExceptionCode.GATEWAY_PATH_UNAVAILABLE), NO_PATH
        except (NoResponse, FrameError) as failure:
            if isinstance(failure, NoResponse) and not self._watch.problems:
                self._silent[unit] = time.monotonic()  # nothing at all: not there, or not listening
            why = "; ".join([*self._watch.problems, str(failure)])
            answer = _exception(pdu[0], ExceptionCode.GATEWAY_TARGET_FAILED_TO_RESPOND)
            outcome = NO_RESPONSE
        else:
            self._silent.pop(unit, None)
            if reply is None:  # a broadcast on the link, or a request no reply is due for (FC08 sub 04)
                answer, outcome, why = None, REPLY, "no reply is due"
            else:
                answer, outcome, why = reply.encode(), REPLY, ""
        if broadcast:
            # Whatever came of it, a broadcast is never answered (spec §2).
            return None, BROADCAST, why if outcome == NO_PATH else "sent to every unit, answered by none"
        return answer, outcome, why

    def _execute(self, unit: int, request: RawRequest):
        link = self.link
        link.stats = self.stats.setdefault(unit, Stats())
        reused = link.client is not None
        try:
            self._open()
            return link.execute(unit, request)
        except (ConnectionClosed, ConnectionFailed):
            if not reused:
                raise
            # A TCP device closes a connection left idle: once more, on a new one.
            self._open()
            return link.execute(unit, request)

    def _open(self) -> Client:
        client = self.link.open()
        client.trace = self._watch
        return client


def _exception(function: int, code: int) -> bytes:
    """An exception response PDU to a request with this function code (spec §3)."""
    return ExceptionResponse(function & 0x7F, code).encode()
