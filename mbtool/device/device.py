"""A simulated Modbus device: the server side of the codec over an in-memory data model.

``sim://`` answers from here in-process and ``mbtool serve`` puts it on a TCP
port or a serial line.  Requests are decoded by the same codec types the
client encodes with, so both sides read the spec the same way.

One ``Device`` is one node on a bus serving one or more unit ids.  Each unit
has its own tables, diagnostic counters and event log (a ``Station``);
stations are made on first use from a shared template, so serving 247 units
costs nothing until they are addressed.  The template also takes every
broadcast write, so a station made later starts from what every other unit
was told (spec §2: unit 0 is all of them).

The ``Device`` chooses the station, keeps the counters and the event log, applies
broadcasts, --read-only and the injected faults, and hands each request to its function's
handler (``mbtool.device.handlers``); what it holds is ``mbtool.device.model``'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

from mbtool.codec.errors import ChecksumError, DecodeError, RequestError
from mbtool.codec.framing import Frame, Framer, Rejected
from mbtool.codec.pdu import (
    ExceptionCode,
    ExceptionResponse,
    Response,
    check_request,
    decode_request,
)
from mbtool.codec.record import record
from mbtool.device.handlers import HANDLERS, RESTART_DATA, SUB_RESTART, changes_state, restart
from mbtool.device.model import (
    BUS_COUNTERS,
    EVENT_RECEIVE,
    EVENT_RECEIVE_BROADCAST,
    EVENT_RECEIVE_COMM_ERROR,
    EVENT_RECEIVE_LISTEN_ONLY,
    EVENT_RECEIVE_OVERRUN,
    EVENT_SEND,
    EVENT_SEND_ABORT,
    EVENT_SEND_BUSY,
    EVENT_SEND_NAK,
    EVENT_SEND_READ_EXCEPTION,
    DataModel,
    Station,
)

if TYPE_CHECKING:
    from mbtool.codec.serial_line import Diagnostics


@record
class Faults:
    """Faults the device itself answers with (the I/O layer adds delay, drop and corruption).

    ``exceptions``: function code -> exception code to answer it with.
    ``busy_until``: a time.monotonic() value; until then every request gets exception 06.
    """

    exceptions: dict | None = None
    busy_until: float = 0.0


class Device:
    """Answers request PDUs for a set of unit ids; unit 0 (broadcast) is applied, never answered."""

    def __init__(
        self,
        model: DataModel | None = None,
        units: frozenset[int] = frozenset({1}),
        unit_models: dict[int, DataModel] | None = None,
    ) -> None:
        self.model = model or DataModel()  # the template every unit starts from
        self.units = frozenset(units)
        self.unit_models = unit_models or {}  # units with data of their own (--data [units.N])
        self.faults = Faults()
        self.read_only = False  # serve --read-only: what changes_state() names gets exception 01
        self.stations: dict[int, Station] = {}
        # Bus-level counters are shared: every node on the line sees every message (spec §4).
        self.bus = dict.fromkeys(BUS_COUNTERS, 0)
        self.served: dict[int, int] = {}  # function code -> requests answered, for the live view
        self.clock: Callable[[], float] = time.monotonic

    # -- stations ----------------------------------------------------------------

    def station(self, unit: int) -> Station:
        station = self.stations.get(unit)
        if station is None:
            if unit in self.unit_models:
                model = self.unit_models[unit]
            elif len(self.units) == 1:
                model = self.model  # one unit (sim://): no copy, start-up stays cheap
            else:
                model = self.model.copy()
            station = self.stations[unit] = Station(unit, model, self.bus)
        return station

    def counters(self, unit: int) -> dict[str, int]:
        """The FC08 counters of a unit as the device reports them."""
        return self.station(unit).reported_counters()

    def ascii_delimiter(self, unit: int) -> int:
        station = self.stations.get(unit)
        return station.ascii_delimiter if station else 0x0A

    # -- entry points ------------------------------------------------------------

    def answer_frame(self, event: Frame | Rejected | object, framer: Framer) -> bytes | None:
        """The reply ADU to a framed request, or None (not a frame, not for us, broadcast)."""
        if isinstance(event, Rejected):
            self.rejected(event)
            return None  # a real slave ignores a frame with a bad checksum (spec §2)
        if not isinstance(event, Frame):
            return None
        unit = event.unit
        if framer.name == "tcp" and unit in (0, 0xFF) and unit not in self.units:
            # Spec §2: on Modbus TCP the unit id is for gateways; 0 and FF address the server
            # itself, which is no broadcast (Modbus TCP implementation guide).  With several
            # units that is the lowest one served.  libmodbus's TCP server answers every unit
            # id from its one set of tables; pymodbus 3.16's answers a unit it was not given,
            # 0 and FF too, with exception 04 (its older single context answered them all):
            # we follow the guide and libmodbus.  With RTU or ASCII framing unit 0 stays the
            # broadcast of handle().
            unit = min(self.units)
        reply = self.handle(unit, event.pdu)
        if reply is None:
            return None
        adu = framer.build(event.unit, reply, event.transaction_id or 0)
        if hasattr(framer, "delimiter"):
            # FC08 sub 03 changes the delimiter of the messages that follow, not of its own echo.
            framer.delimiter = self.ascii_delimiter(event.unit)
        return adu

    def rejected(self, event: Rejected) -> None:
        """Bytes on the line that made no frame: a CRC/LRC error is a bus communication error."""
        if isinstance(event.error, ChecksumError):
            self._count_bus("bus_comm_errors")
            for station in self.stations.values():
                station.log(EVENT_RECEIVE | EVENT_RECEIVE_COMM_ERROR | self._listen_bit(station))
        if len(event.data) > 256:
            self.overrun()

    def overrun(self) -> None:
        """More characters than a frame can hold arrived (spec §4 sub 12)."""
        self._count_bus("bus_char_overruns")
        for station in self.stations.values():
            station.log(EVENT_RECEIVE | EVENT_RECEIVE_OVERRUN | self._listen_bit(station))

    def handle(self, unit: int, pdu: bytes) -> bytes | None:
        """The reply PDU to a request PDU, or None when no reply is due."""
        self._count_bus("bus_messages")
        if unit == 0:
            self._broadcast(pdu)
            return None
        if unit not in self.units:
            return None  # a frame for another slave on the bus
        station = self.station(unit)
        station.count("slave_messages")
        station.log(EVENT_RECEIVE | self._listen_bit(station))
        reply = self._reply(station, pdu)
        if reply is None:
            station.count("slave_no_response")
            return None
        code = pdu[0] if pdu else 0
        if isinstance(reply, ExceptionResponse):
            self._count_exception(station, reply.exception_code)
        elif code not in (0x0B, 0x0C):
            # FC11: not incremented for exceptions, polls or fetch-event-counter commands.
            station.event_count = (station.event_count + 1) & 0xFFFF
        station.log(EVENT_SEND | self._send_bits(reply))
        self.served[code] = self.served.get(code, 0) + 1
        return reply.encode()

    # -- bookkeeping -----------------------------------------------------------------

    def _count_bus(self, name: str) -> None:
        self.bus[name] = (self.bus[name] + 1) & 0xFFFF

    @staticmethod
    def _listen_bit(station: Station) -> int:
        return EVENT_RECEIVE_LISTEN_ONLY if station.listen_only else 0

    @staticmethod
    def _send_bits(reply: Response | ExceptionResponse) -> int:
        if not isinstance(reply, ExceptionResponse):
            return 0
        code = reply.exception_code
        if code <= 3:
            return EVENT_SEND_READ_EXCEPTION
        if code == 4:
            return EVENT_SEND_ABORT
        if code in (5, 6):
            return EVENT_SEND_BUSY
        if code == 7:
            return EVENT_SEND_NAK
        return 0

    @staticmethod
    def _count_exception(station: Station, code: int) -> None:
        station.count("bus_exceptions")
        if code == ExceptionCode.SERVER_DEVICE_BUSY:
            station.count("slave_busy")
        elif code == ExceptionCode.NEGATIVE_ACKNOWLEDGE:
            station.count("slave_naks")

    def _broadcast(self, pdu: bytes) -> None:
        """Unit 0: a write goes to every unit served, nobody answers (spec §2)."""
        try:
            request = decode_request(pdu)
        except (RequestError, DecodeError):
            return
        if not request.broadcastable or self.read_only:  # a broadcast is always a write
            return
        models = {id(self.model): self.model}
        for unit in self.units:
            station = self.stations.get(unit)
            if station is not None:
                station.count("slave_messages")
                station.count("slave_no_response")
                station.log(EVENT_RECEIVE | EVENT_RECEIVE_BROADCAST | self._listen_bit(station))
                if station.listen_only:
                    continue
                models[id(station.model)] = station.model
            elif unit in self.unit_models:
                models[id(self.unit_models[unit])] = self.unit_models[unit]
        handler = HANDLERS[request.function_code]
        for model in models.values():
            # Stations not yet made share the template: writing it once reaches them all.
            try:
                handler(Station(0, model, self.bus), request)
            except RequestError:
                pass  # addresses a sparse unit does not have: nothing to write, nobody to tell

    def _reply(self, station: Station, pdu: bytes) -> Response | ExceptionResponse | None:
        code = pdu[0] if pdu else 0
        try:
            request = check_request(pdu)
        except RequestError as error:
            request = None
            failure = ExceptionResponse(code, error.exception_code)
        if station.listen_only:
            # Listen-only: nothing is done and nothing answered, except a restart (spec §4 sub 04).
            # FC 08's request is a Diagnostics (its module loads only when FC 08 is used).
            asked = cast("Diagnostics", request) if code == 0x08 and request is not None else None
            if asked is not None and asked.sub_function == SUB_RESTART and asked.data in RESTART_DATA:
                restart(station, asked.data)  # other data would get exception 03
            return None
        if self.read_only and changes_state(pdu):
            return ExceptionResponse(code, ExceptionCode.ILLEGAL_FUNCTION)
        if request is None:
            return failure
        injected = self._injected(code)
        if injected is not None:
            return ExceptionResponse(code, injected)
        handler = HANDLERS.get(code)
        if handler is None:
            return ExceptionResponse(code, ExceptionCode.ILLEGAL_FUNCTION)
        try:
            return handler(station, request)
        except RequestError as error:
            return ExceptionResponse(code, error.exception_code)

    def _injected(self, code: int) -> int | None:
        if self.faults.busy_until and self.clock() < self.faults.busy_until:
            return ExceptionCode.SERVER_DEVICE_BUSY
        if self.faults.exceptions:
            return self.faults.exceptions.get(code)
        return None
