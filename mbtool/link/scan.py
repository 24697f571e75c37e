"""The scan algorithm: which unit ids answer on a bus, at which serial settings.

One probe per unit id.  Any reply, and any Modbus exception, proves a device is
there (spec §3: an exception response is a valid answer); silence means nobody
is.  Bytes that make no valid frame ("garbled") mean something is there but the
settings are probably wrong, so they are kept apart.  Exceptions 0A and 0B are a
gateway saying the unit behind it is unreachable (spec §3), so they prove the
opposite.  A reply that comes after its timeout arrives while the next unit is
probed; it is recognised by its unit id and reported as "late".

What is shown is not decided here: ``Scan`` tells a ``Found`` and a ``Progress``
(the CLI's ``mbtool scan`` draws them).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from typing import Protocol

from mbtool.codec import data_access
from mbtool.codec.data_access import BitsResponse, RegistersResponse
from mbtool.codec.device_id import DeviceIdentificationResponse, ReadDeviceIdCode, ReadDeviceIdentification
from mbtool.codec.errors import FrameError, MismatchError, ModbusException, ProtocolError, exception_name
from mbtool.codec.exchange import Trace
from mbtool.codec.framer import Frame
from mbtool.codec.framing import make_framer
from mbtool.codec.pdu import ExceptionResponse, printable, text_of
from mbtool.codec.record import record, replace
from mbtool.codec.serial_line import (
    DEFAULT_QUERY_DATA,
    Diagnostics,
    DiagnosticsResponse,
    DiagnosticSubFunction,
    ReportSlaveId,
    ReportSlaveIdResponse,
)
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link.connection import changed, framer_name, open_client
from mbtool.link.managed import LOST, Backoff, ManagedLink
from mbtool.link.stats import Stats
from mbtool.link.transport import ConnectionClosed, SerialSettings

GATEWAY_EXCEPTIONS = (0x0A, 0x0B)  # spec §3: path unavailable, target failed to respond

READS = ("read-holding-registers", "read-input-registers", "read-coils", "read-discrete-inputs")
PROBES = READS + ("report-id", "device-id", "return-query-data")


class Found(Protocol):
    """Where the scan reports as it goes."""

    def found(self, answer: Answer) -> None: ...

    def garbled(self, answer: Answer) -> None: ...

    def note(self, text: str) -> None: ...


class Progress(Protocol):
    def at(self, setting: Setting | None, unit: int) -> None: ...

    def advance(self, steps: int = 1) -> None: ...

    def found(self, count: int) -> None: ...


# --- what was found -----------------------------------------------------------------------


@record
class Setting(SerialSettings):
    """One serial setting of a sweep; ``error`` when the port refused it."""

    error: str = ""


@record
class Answer:
    """How one unit answered one probe: reply, exception or garbled."""

    unit: int
    answer: str  # "reply" | "exception" | "garbled"
    text: str  # for people
    fields: dict  # for scripts (JSON)
    ms: float | None = None  # probe to answer; None for a late answer
    setting: Setting | None = None  # when sweeping
    late: bool = False  # answered after its timeout, during a later probe


class Tally:
    def __init__(self) -> None:
        self.found: list[Answer] = []
        self.garbled: list[Answer] = []
        self.settings: list[Setting] = []
        self.probes = 0
        self.silent: set[tuple[int, int]] = set()  # (setting index, unit) that never answered
        self.gateway = 0  # units a gateway said it cannot reach (exception 0A/0B)
        self.interrupted = False
        self.transactions = Stats()  # what became of each probe, as every summary counts them


# --- probing ------------------------------------------------------------------------------


def probe_request(function: str, address: int, count: int):
    """The request each unit is asked; built before anything is opened (bad input: exit 2)."""
    if function in READS:
        kind = {
            "read-holding-registers": data_access.ReadHoldingRegisters,
            "read-input-registers": data_access.ReadInputRegisters,
            "read-coils": data_access.ReadCoils,
            "read-discrete-inputs": data_access.ReadDiscreteInputs,
        }[function]
        return kind(address, count)
    if function == "report-id":
        return ReportSlaveId()
    if function == "device-id":
        return ReadDeviceIdentification(ReadDeviceIdCode.BASIC, 0)

    return Diagnostics(DiagnosticSubFunction.RETURN_QUERY_DATA, DEFAULT_QUERY_DATA)


def _reply_answer(unit: int, reply, ms: float | None) -> Answer:
    """What a reply says about the device, for people (text) and for scripts (fields)."""

    fields: dict = {}
    text = "reply"
    if isinstance(reply, RegistersResponse):
        fields = {"values": list(reply.registers)}
        text = "registers " + " ".join(str(v) for v in reply.registers)
    elif isinstance(reply, BitsResponse):
        fields = {"values": list(reply.bits)}
        text = "bits " + " ".join("1" if bit else "0" for bit in reply.bits)
    elif isinstance(reply, ReportSlaveIdResponse):
        fields = {
            "slave_id": reply.slave_id,
            "run_indicator": reply.run_indicator,
            "extra_hex": reply.extra.hex(" ").upper(),
            "extra_text": printable(reply.extra),
        }
        text = f"slave id {reply.slave_id}, run {'ON' if reply.run_indicator else 'OFF'}"
        if reply.extra:
            text += f", {printable(reply.extra)}"
    elif isinstance(reply, DeviceIdentificationResponse):
        fields = {"objects": {name: text_of(value) for name, value in reply.named_objects()}}
        text = " / ".join(fields["objects"].values()) or "no objects"
    elif isinstance(reply, DiagnosticsResponse):
        fields = {"echo": reply.data.hex(" ").upper()}
        text = "echo " + fields["echo"]
    return Answer(unit, "reply", text, fields, ms)


class Listener(Trace):
    """Passes the trace on (--hex) and keeps the frames that answered no probe: late replies.

    A reply that misses its timeout arrives during a later probe, either as a frame
    the client discards (another unit, an old transaction id) or as stale bytes
    dropped before the next request; both reach the trace, and are read here with a
    framer of their own.
    """

    def __init__(self, inner, framer_name: str) -> None:
        self.inner = inner
        self.framer_name = framer_name
        self.strays: list = []  # codec Frames

    def sent(self, adu: bytes) -> None:
        self.inner.sent(adu)

    def received(self, adu: bytes, note: str = "") -> None:
        self.inner.received(adu, note)
        if note:
            self.strays += frames_in(self.framer_name, adu)

    def rejected(self, data: bytes, error: FrameError) -> None:
        self.inner.rejected(data, error)
        self.strays += frames_in(self.framer_name, data)

    def take(self) -> list:
        strays, self.strays = self.strays, []
        return strays


def frames_in(framer_name: str, data: bytes) -> list:
    """The whole, valid frames in ``data``, read as replies."""

    framer = make_framer(framer_name)
    framer.feed(data)
    frames = []
    for _ in range(len(data) + 1):  # every event consumes bytes: this bounds the loop
        event = framer.next_event() or framer.silence()
        if event is None:
            break
        if isinstance(event, Frame):
            frames.append(event)
    return frames


def ask(execute: Callable, unit: int, request, framer_name: str) -> Answer | str:
    """Probe one unit through ``execute`` (the client's, counted): an Answer, or why there is
    none ("silent" or "gateway").

    Link failures (ConnectionFailed, a closed connection, OSError) are the caller's.
    """
    began = time.monotonic()
    try:
        reply = execute(unit, request)
    except ModbusException as exception:
        return _exception_answer(unit, exception.exception_code, _ms(began)) or "gateway"
    except ConnectionClosed:
        raise
    except NoResponse:
        return "silent"
    except MismatchError as error:
        # A valid frame from another unit is a late reply to an earlier probe (the
        # Listener credits it), not an answer from this one.
        frames = frames_in(framer_name, error.data)
        if frames and all(frame.unit != unit for frame in frames):
            return "silent"
        return Answer(unit, "garbled", str(error), {"error": str(error)})
    except FrameError as error:
        return Answer(unit, "garbled", str(error), {"error": str(error)})
    return _reply_answer(unit, reply, _ms(began))


def _ms(began: float) -> float:
    return round((time.monotonic() - began) * 1000, 1)


def _late(frame, request, probed: set[int], found: set[int]) -> Answer | None:
    """A stray frame as the late answer of a unit probed earlier on this link, if it is one."""

    if frame.unit not in probed or frame.unit in found:
        return None
    try:
        reply = request.decode_response(frame.pdu)
    except ProtocolError:
        return None  # not an answer to this probe (another function, or garbled)
    if isinstance(reply, ExceptionResponse):
        answer = _exception_answer(frame.unit, reply.exception_code, None)
    else:
        answer = _reply_answer(frame.unit, reply, None)
    if answer is None:
        return None
    return replace(answer, text=f"{answer.text} (late: answered after the timeout, raise -t)", late=True)


def _exception_answer(unit: int, code: int, ms: float | None) -> Answer | None:
    """An exception proves a device is there, except a gateway's 0A/0B: nobody behind it answered."""

    if code in GATEWAY_EXCEPTIONS:
        return None
    name = exception_name(code)
    return Answer(unit, "exception", f"{code:02X} {name}", {"exception": code, "exception_name": name}, ms)


# --- the sweep ----------------------------------------------------------------------------


class Scan:
    def __init__(
        self,
        connection,
        request,
        units: list[int],
        settings: list[Setting],
        sweeping: bool,
        first: bool,
        output: Found,
        trace: Callable | None = None,
    ) -> None:
        self.connection = connection
        self.request = request
        self.units = units
        self.settings = settings
        self.sweeping = sweeping
        self.first = first
        self.output = output
        self.trace = trace  # makes each link's trace from its framer (--hex)
        self.tally = Tally()

    def run(self, progress: Progress) -> Tally:
        """Probe every unit at every setting (until --first is met); what answered, counted."""
        self.progress = progress
        tally = self.tally
        try:
            for setting in self.settings:
                tally.settings.append(setting)
                if self._link(setting):
                    break
        except KeyboardInterrupt:
            tally.interrupted = True
        return tally

    def _link_at(self, setting: Setting) -> ManagedLink:
        """The link at one setting: opened again at once when it is lost (a gateway hanging up
        on an unknown unit), each transaction counted in the tally."""
        # unit: a real one, for open_client's broadcast check (the option holds the whole set).
        connection = changed(self.connection, baud=setting.baud, parity=setting.parity, unit=self.units[0])

        @contextmanager
        def opened():
            with open_client(connection, self.request.name, trace=self.trace) as client:
                client.trace = Listener(client.trace, framer_name(connection))
                yield client

        return ManagedLink(opened, Backoff(0.0), self.tally.transactions)

    def _link(self, setting: Setting) -> bool:
        """Probe every unit at one setting; True when the scan should stop (--first)."""

        tally = self.tally
        name = framer_name(self.connection)
        link = self._link_at(setting)
        try:
            try:
                link.open()
            except ConnectionFailed as error:
                if not self.sweeping:
                    raise
                self._refused(setting, str(error), len(self.units))
                return False
            probed: set[int] = set()
            found: set[int] = set()
            here = len(tally.settings) - 1
            for index, unit in enumerate(self.units):
                self.progress.at(setting if self.sweeping else None, unit)
                try:
                    outcome = ask(link.execute, unit, self.request, name)
                except LOST as error:
                    # The link broke (a gateway hanging up on an unknown unit, a cable
                    # pulled): count this unit silent and go on over a new link.
                    try:
                        link.open()
                    except ConnectionFailed as again:
                        self._refused(setting, str(again), len(self.units) - index)
                        return False
                    outcome = "silent"
                    self.output.note(f"unit {unit}: {error}; link reopened")
                tally.probes += 1
                self.progress.advance()
                # Only units asked before this one can answer late; a stray frame from this
                # unit is something else (the adapter's echo of the probe, an old transaction).
                client = link.client
                assert client is not None and isinstance(client.trace, Listener)  # opened() made them
                answers = [_late(frame, self.request, probed, found) for frame in client.trace.take()]
                probed.add(unit)
                if outcome == "silent":
                    tally.silent.add((here, unit))
                elif outcome == "gateway":
                    tally.gateway += 1
                elif isinstance(outcome, Answer):
                    answers.append(outcome)
                for answer in answers:
                    if answer is not None:
                        self._record(replace(answer, setting=setting if self.sweeping else None), here, found)
                if self.first and tally.found:
                    return True
            return False
        finally:
            link.close()

    def _record(self, answer: Answer, here: int, found: set[int]) -> None:
        """Keep an answer: garbled ones apart, each unit found once per setting."""
        tally = self.tally
        if answer.answer == "garbled":
            tally.garbled.append(answer)
            self.output.garbled(answer)
            return
        if answer.unit in found:
            return
        tally.silent.discard((here, answer.unit))  # a late answer: silent no more
        found.add(answer.unit)
        tally.found.append(answer)
        self.output.found(answer)
        self.progress.found(len(tally.found))

    def _refused(self, setting: Setting, error: str, skipped: int) -> None:
        self.tally.settings[-1] = replace(setting, error=error)
        self.output.note(f"{setting}: {error}" if self.sweeping else error)
        self.progress.advance(skipped)
