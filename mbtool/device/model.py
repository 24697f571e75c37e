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

Tables are a bytearray (bits) and array("H") (registers): no Python object
per item, so a one-shot ``-p sim://`` command pays microseconds for them.
"""

from __future__ import annotations

import struct
import time
from array import array
from collections import deque
from collections.abc import Callable

from mbtool.codec.errors import ChecksumError, DecodeError, RequestError
from mbtool.codec.framing import Frame, Framer, Rejected
from mbtool.codec.pdu import (
    ExceptionCode,
    ExceptionResponse,
    Response,
    decode_request,
    function_type,
)
from mbtool.codec.record import record

TABLE_SIZE = 0x10000  # every table spans the whole 16-bit address space (spec §1)
FILE_SIZE = 10000  # records 0..9999 per file (spec §1, FC20/21)
MAX_EVENTS = 64  # FC12 log length (spec §3)
MAX_PDU = 253

# Event bytes of the FC12 log (spec §5).
EVENT_RECEIVE = 0x80
EVENT_RECEIVE_COMM_ERROR = 0x02
EVENT_RECEIVE_OVERRUN = 0x10
EVENT_RECEIVE_LISTEN_ONLY = 0x20
EVENT_RECEIVE_BROADCAST = 0x40
EVENT_SEND = 0x40
EVENT_SEND_READ_EXCEPTION = 0x01  # codes 1-3
EVENT_SEND_ABORT = 0x02  # code 4
EVENT_SEND_BUSY = 0x04  # codes 5-6
EVENT_SEND_NAK = 0x08  # code 7 (bit 5, "in listen-only mode", never applies: nothing is sent then)
EVENT_LISTEN_ONLY = 0x04
EVENT_RESTART = 0x00

# FC08 sub-functions (spec §4), as plain ints: the device must not pay for the enum.
SUB_QUERY = 0x00
SUB_RESTART = 0x01
RESTART_DATA = (b"\x00\x00", b"\xff\x00")  # sub 01: keep the event log, or clear it too
SUB_DIAG_REGISTER = 0x02
SUB_ASCII_DELIMITER = 0x03
SUB_LISTEN_ONLY = 0x04
SUB_CLEAR_COUNTERS = 0x0A
SUB_CLEAR_OVERRUN = 0x14
SUB_MODBUS_PLUS = 0x15
# Sub-functions 0B..13 return one counter each (spec §4), in this order.
COUNTER_SUBS = {
    0x0B: "bus_messages",
    0x0C: "bus_comm_errors",
    0x0D: "bus_exceptions",
    0x0E: "slave_messages",
    0x0F: "slave_no_response",
    0x10: "slave_naks",
    0x11: "slave_busy",
    0x12: "bus_char_overruns",
    0x13: "iop_overruns",
}
BUS_COUNTERS = ("bus_messages", "bus_comm_errors", "bus_char_overruns")

# The function codes that change data (spec §1's write column, and FC21 for files):
# a read-only device (serve --read-only) answers them exception 01, a function it does not do.
WRITE_FUNCTIONS = frozenset({0x05, 0x06, 0x0F, 0x10, 0x15, 0x16, 0x17})

# Read Device Identification (FC43/14): basic 00-02, regular 03-06, extended 80-FF.
DEFAULT_OBJECTS = {
    0x00: b"mbtool",
    0x01: b"MBTOOL-SIM",
    0x02: b"1.0",
    0x03: b"https://example.invalid/mbtool",
    0x04: b"mbtool serve",
    0x05: b"simulated device",
    0x06: b"mbtool",
}
OBJECT_KEYS = {
    "vendor_name": 0x00,
    "product_code": 0x01,
    "revision": 0x02,
    "vendor_url": 0x03,
    "product_name": 0x04,
    "model_name": 0x05,
    "user_application_name": 0x06,
}


class DataModel:
    """The tables of spec §1, plus what the serial-line function codes report about the device."""

    def __init__(self) -> None:
        self.coils = bytearray(TABLE_SIZE)
        self.discrete_inputs = bytearray(TABLE_SIZE)
        self.holding_registers = array("H", bytes(2 * TABLE_SIZE))
        self.input_registers = array("H", bytes(2 * TABLE_SIZE))
        self.files: dict[int, array] = {}  # file number -> 10000 registers, made on first write
        self.exception_status = 0  # FC07: eight device-defined bits
        self.diagnostic_register = 0  # FC08 sub 02
        self.slave_id: int | None = None  # FC17; None: the unit id
        self.run_indicator = True
        self.slave_id_extra = b"mbtool"
        self.objects: dict[int, bytes] = dict(DEFAULT_OBJECTS)  # FC43/14
        # A sparse data file (README, "Simulating a device"): what it defines, per table name
        # and per file number, 1 for each address it lists.  None: every address exists.
        self.defined: dict[str | int, bytearray] | None = None

    def copy(self) -> DataModel:
        other = DataModel.__new__(DataModel)
        other.coils = bytearray(self.coils)
        other.discrete_inputs = bytearray(self.discrete_inputs)
        other.holding_registers = array("H", self.holding_registers)
        other.input_registers = array("H", self.input_registers)
        other.files = {number: array("H", values) for number, values in self.files.items()}
        other.exception_status = self.exception_status
        other.diagnostic_register = self.diagnostic_register
        other.slave_id = self.slave_id
        other.run_indicator = self.run_indicator
        other.slave_id_extra = self.slave_id_extra
        other.objects = dict(self.objects)
        other.defined = None if self.defined is None else {k: bytearray(v) for k, v in self.defined.items()}
        return other

    def file(self, number: int, create: bool) -> array | None:
        values = self.files.get(number)
        if values is None and create:
            values = self.files[number] = array("H", bytes(2 * FILE_SIZE))
        return values

    def defines(self, key: str | int, size: int) -> bytearray | None:
        """The mask a sparse data file marks its addresses in (a table name or a file number);
        None when the model is not sparse."""
        if self.defined is None:
            return None
        return self.defined.setdefault(key, bytearray(size))

    def require(self, key: str | int, start: int, count: int) -> None:
        """Exception 02 unless ``count`` addresses from ``start`` exist: all do, unless a sparse
        data file left some undefined, as a real device has gaps in its address map."""
        if self.defined is None:
            return
        mask = self.defined.get(key)
        if mask is None or mask.find(0, start, start + count) != -1:
            table = f"file {key}" if isinstance(key, int) else key.replace("_", " ")
            raise RequestError(
                f"{table} {start}..{start + count - 1} is not all defined", ExceptionCode.ILLEGAL_DATA_ADDRESS
            )


def demo_model() -> DataModel:
    """The data ``sim://`` starts with, so a first read shows something (README lists it)."""
    model = DataModel()
    for i in range(100):
        model.holding_registers[i] = i
        model.input_registers[i] = 1000 + i
        model.coils[i] = i % 2 == 0
        model.discrete_inputs[i] = i % 3 == 0
    # A float32 21.5 (°C, say) at holding registers 100-101, big-endian words (ABCD),
    # and the same value word-swapped (CDAB) at 102-103, to try --type and --order on.
    model.holding_registers[100:104] = array("H", [0x41AC, 0x0000, 0x0000, 0x41AC])
    # A FIFO queue at 200 (FC24): count at 200, entries from 201 on.
    model.holding_registers[200:204] = array("H", [3, 0x0101, 0x0202, 0x0303])
    model.exception_status = 0x6D  # seed 002's FC07 example reply
    return model


@record
class Faults:
    """Faults the device itself answers with (the I/O layer adds delay, drop and corruption).

    ``exceptions``: function code -> exception code to answer it with.
    ``busy_until``: a time.monotonic() value; until then every request gets exception 06.
    """

    exceptions: dict | None = None
    busy_until: float = 0.0


class Station:
    """One unit id: its tables, its diagnostic counters and its event log (spec §4, §5)."""

    def __init__(self, unit: int, model: DataModel) -> None:
        self.unit = unit
        self.model = model
        self.counters = dict.fromkeys(COUNTER_SUBS.values(), 0)
        self.event_count = 0  # FC11: successful completions, not counting FC11/FC12 polls
        self.events: deque[int] = deque(maxlen=MAX_EVENTS)  # newest first (appendleft)
        self.listen_only = False
        self.ascii_delimiter = 0x0A

    def count(self, name: str) -> None:
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    def log(self, event: int) -> None:
        self.events.appendleft(event)

    def clear_counters(self) -> None:
        """The communication event counters (FC08 sub 01 and 0A); not the diagnostic register."""
        for name in self.counters:
            self.counters[name] = 0
        self.event_count = 0


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
        self.read_only = False  # serve --read-only: WRITE_FUNCTIONS get exception 01
        self.stations: dict[int, Station] = {}
        # Bus-level counters are shared: every node on the line sees every message (spec §4).
        self.bus = dict.fromkeys(BUS_COUNTERS, 0)
        self.served: dict[int, int] = {}  # function code -> requests answered, for the live view
        self.clock: Callable[[], float] = time.monotonic
        self._handlers: dict[int, Callable] = {
            0x01: lambda s, r: self._read_bits(s.model, r, "coils"),
            0x02: lambda s, r: self._read_bits(s.model, r, "discrete_inputs"),
            0x03: lambda s, r: self._read_registers(s.model, r, "holding_registers"),
            0x04: lambda s, r: self._read_registers(s.model, r, "input_registers"),
            0x05: self._write_single_coil,
            0x06: self._write_single_register,
            0x07: self._read_exception_status,
            0x08: self._diagnostics,
            0x0B: self._comm_event_counter,
            0x0C: self._comm_event_log,
            0x0F: self._write_multiple_coils,
            0x10: self._write_multiple_registers,
            0x11: self._report_slave_id,
            0x14: self._read_file_record,
            0x15: self._write_file_record,
            0x16: self._mask_write_register,
            0x17: self._read_write_registers,
            0x18: self._read_fifo_queue,
            0x2B: self._read_device_identification,
        }

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
            station = self.stations[unit] = Station(unit, model)
        return station

    def counters(self, unit: int) -> dict[str, int]:
        """The FC08 counters of a unit as the device reports them."""
        station = self.station(unit)
        return {**station.counters, **{name: self.bus[name] for name in BUS_COUNTERS}}

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
        handler = self._handlers[request.function_code]
        for model in models.values():
            # Stations not yet made share the template: writing it once reaches them all.
            try:
                handler(Station(0, model), request)
            except RequestError:
                pass  # addresses a sparse unit does not have: nothing to write, nobody to tell

    def _reply(self, station: Station, pdu: bytes) -> Response | ExceptionResponse | None:
        code = pdu[0] if pdu else 0
        try:
            request = decode_request(pdu)
        except RequestError as error:
            request = None
            failure = ExceptionResponse(code, error.exception_code)
        except DecodeError:
            request = None
            known = function_type(code) is not None and code in self._handlers
            failure = ExceptionResponse(
                code, ExceptionCode.ILLEGAL_DATA_VALUE if known else ExceptionCode.ILLEGAL_FUNCTION
            )
        if station.listen_only:
            # Listen-only: nothing is done and nothing answered, except a restart (spec §4 sub 04).
            restart = request is not None and code == 0x08 and request.sub_function == SUB_RESTART
            if restart and request.data in RESTART_DATA:  # other data would get exception 03
                self._restart(station, request.data)
            return None
        if self.read_only and code in WRITE_FUNCTIONS:
            # Before the request's own checks: a device without the function answers 01 to
            # any form of it, as it would to a function code it does not know.
            return ExceptionResponse(code, ExceptionCode.ILLEGAL_FUNCTION)
        if request is None:
            return failure
        injected = self._injected(code)
        if injected is not None:
            return ExceptionResponse(code, injected)
        handler = self._handlers.get(code)
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

    # -- FC 01-06, 15, 16, 22, 23, 24: the tables ------------------------------------

    @staticmethod
    def _read_bits(model: DataModel, request, name: str):
        from mbtool.codec.data_access import BitsResponse

        model.require(name, request.address, request.count)
        table = getattr(model, name)
        bits = tuple(bool(b) for b in table[request.address : request.address + request.count])
        return BitsResponse(request.function_code, bits)

    @staticmethod
    def _read_registers(model: DataModel, request, name: str):
        from mbtool.codec.data_access import RegistersResponse

        model.require(name, request.address, request.count)
        table = getattr(model, name)
        return RegistersResponse(
            request.function_code, tuple(table[request.address : request.address + request.count])
        )

    @staticmethod
    def _write_single_coil(station: Station, request):
        station.model.require("coils", request.address, 1)
        station.model.coils[request.address] = request.on
        return request

    @staticmethod
    def _write_single_register(station: Station, request):
        station.model.require("holding_registers", request.address, 1)
        station.model.holding_registers[request.address] = request.value
        return request

    @staticmethod
    def _write_multiple_coils(station: Station, request):
        from mbtool.codec.data_access import WriteMultipleResponse

        station.model.require("coils", request.address, len(request.values))
        station.model.coils[request.address : request.address + len(request.values)] = bytes(request.values)
        return WriteMultipleResponse(request.function_code, request.address, len(request.values))

    @staticmethod
    def _write_multiple_registers(station: Station, request):
        from mbtool.codec.data_access import WriteMultipleResponse

        station.model.require("holding_registers", request.address, len(request.values))
        end = request.address + len(request.values)
        station.model.holding_registers[request.address : end] = array("H", request.values)
        return WriteMultipleResponse(request.function_code, request.address, len(request.values))

    @staticmethod
    def _mask_write_register(station: Station, request):
        station.model.require("holding_registers", request.address, 1)
        table = station.model.holding_registers
        table[request.address] = request.result(table[request.address])
        return request

    @staticmethod
    def _read_write_registers(station: Station, request):
        """FC23: the write is done before the read (spec §3), once both ranges are known to exist."""
        from mbtool.codec.data_access import RegistersResponse

        model = station.model
        model.require("holding_registers", request.write_address, len(request.values))
        model.require("holding_registers", request.read_address, request.read_count)
        table = model.holding_registers
        table[request.write_address : request.write_address + len(request.values)] = array(
            "H", request.values
        )
        end = request.read_address + request.read_count
        return RegistersResponse(request.function_code, tuple(table[request.read_address : end]))

    @staticmethod
    def _read_fifo_queue(station: Station, request):
        """FC24: the FIFO pointer register holds the count, the entries follow it (README)."""
        from mbtool.codec.data_access import MAX_FIFO_COUNT, ReadFifoQueueResponse

        model = station.model
        model.require("holding_registers", request.address, 1)
        table = model.holding_registers
        count = table[request.address]
        if count > MAX_FIFO_COUNT:
            raise RequestError(f"FIFO count {count} exceeds 31", ExceptionCode.ILLEGAL_DATA_VALUE)
        start = request.address + 1
        if start + count > TABLE_SIZE:
            raise RequestError("FIFO runs past 65535", ExceptionCode.ILLEGAL_DATA_ADDRESS)
        model.require("holding_registers", start, count)
        return ReadFifoQueueResponse(tuple(table[start : start + count]))

    # -- FC 20, 21: file records --------------------------------------------------------

    @staticmethod
    def _read_file_record(station: Station, request):
        from mbtool.codec.file_record import ReadFileRecordResponse

        for group in request.groups:
            station.model.require(group.file, group.record, group.length)
        records = []
        for group in request.groups:
            values = station.model.file(group.file, create=False)
            if values is None:
                records.append((0,) * group.length)  # a file never written reads as zeros
            else:
                records.append(tuple(values[group.record : group.record + group.length]))
        return ReadFileRecordResponse(tuple(records))

    @staticmethod
    def _write_file_record(station: Station, request):
        for group in request.groups:  # every group exists before any is written
            station.model.require(group.file, group.record, len(group.values))
        for group in request.groups:
            values = station.model.file(group.file, create=True)
            values[group.record : group.record + len(group.values)] = array("H", group.values)
        return request  # the reply is an echo (spec §3)

    # -- FC 07, 08, 11, 12, 17: the serial line ------------------------------------------

    @staticmethod
    def _read_exception_status(station: Station, request):
        from mbtool.codec.serial_line import ExceptionStatusResponse

        return ExceptionStatusResponse(station.model.exception_status & 0xFF)

    def _diagnostics(self, station: Station, request):
        from mbtool.codec.serial_line import DiagnosticsResponse

        sub, data = int(request.sub_function), request.data
        if sub == SUB_QUERY:
            return DiagnosticsResponse(sub, data)
        zero = data == b"\x00\x00"
        if sub == SUB_RESTART:
            if data not in RESTART_DATA:
                raise RequestError("restart data is neither 0000 nor FF00")
            self._restart(station, data)
            return DiagnosticsResponse(sub, data)
        if sub == SUB_ASCII_DELIMITER:
            # Spec §4: the data is CHAR 00.  pymodbus (3.16) sends 00 CHAR; a bench device
            # should take both rather than refuse a common master.
            if data[1] == 0:
                station.ascii_delimiter = data[0]
            elif data[0] == 0:
                station.ascii_delimiter = data[1]
            else:
                raise RequestError("delimiter data is not CHAR 00")
            return DiagnosticsResponse(sub, data)
        if sub == SUB_MODBUS_PLUS:
            if data == b"\x00\x03":
                return DiagnosticsResponse(sub, data + bytes([2 * 54]) + bytes(2 * 54))
            if data == b"\x00\x04":
                return DiagnosticsResponse(sub, data)
            raise RequestError("Modbus Plus operation is neither 0003 nor 0004")
        if sub not in COUNTER_SUBS and sub not in (
            SUB_DIAG_REGISTER,
            SUB_LISTEN_ONLY,
            SUB_CLEAR_COUNTERS,
            SUB_CLEAR_OVERRUN,
        ):
            raise RequestError(f"sub-function {sub:02X} is not supported", ExceptionCode.ILLEGAL_FUNCTION)
        if not zero:
            raise RequestError(f"sub-function {sub:02X} takes data 0000")
        if sub == SUB_LISTEN_ONLY:
            station.listen_only = True
            station.log(EVENT_LISTEN_ONLY)
            return None  # never answered (spec §4)
        if sub == SUB_CLEAR_COUNTERS:
            self._clear_counters(station)
            station.model.diagnostic_register = 0  # sub 0A alone clears it too (spec §4)
            return DiagnosticsResponse(sub, data)
        if sub == SUB_CLEAR_OVERRUN:
            self.bus["bus_char_overruns"] = 0
            return DiagnosticsResponse(sub, data)
        if sub == SUB_DIAG_REGISTER:
            value = station.model.diagnostic_register
        else:
            value = self.counters(station.unit)[COUNTER_SUBS[sub]]
        return DiagnosticsResponse(sub, struct.pack(">H", value))

    def _clear_counters(self, station: Station) -> None:
        station.clear_counters()
        for name in BUS_COUNTERS:
            self.bus[name] = 0

    def _restart(self, station: Station, data: bytes) -> None:
        """Sub 01: leave listen-only, clear the communication event counters (and the log with
        FF00), log a restart.  The diagnostic register stays: only sub 0A clears it (spec §4)."""
        station.listen_only = False
        self._clear_counters(station)
        if data == b"\xff\x00":
            station.events.clear()
        station.log(EVENT_RESTART)

    @staticmethod
    def _comm_event_counter(station: Station, request):
        from mbtool.codec.serial_line import CommEventCounterResponse

        return CommEventCounterResponse(0x0000, station.event_count)

    def _comm_event_log(self, station: Station, request):
        from mbtool.codec.serial_line import CommEventLogResponse

        return CommEventLogResponse(
            0x0000, station.event_count, self.bus["bus_messages"], bytes(station.events)
        )

    @staticmethod
    def _report_slave_id(station: Station, request):
        from mbtool.codec.serial_line import ReportSlaveIdResponse

        model = station.model
        slave_id = station.unit if model.slave_id is None else model.slave_id
        return ReportSlaveIdResponse(slave_id & 0xFF, model.run_indicator, model.slave_id_extra)

    @staticmethod
    def _read_device_identification(station: Station, request):
        """FC43/14: stream access 1-3 from the object asked for, 4 one object (spec §3)."""
        from mbtool.codec.device_id import DeviceIdentificationResponse

        objects = station.model.objects
        extended = any(object_id >= 0x80 for object_id in objects)
        conformity = 0x83 if extended else 0x82  # stream and individual access
        code = int(request.read_code)
        if code == 4:
            if request.object_id not in objects:
                raise RequestError(
                    f"object {request.object_id:02X} does not exist", ExceptionCode.ILLEGAL_DATA_ADDRESS
                )
            value = objects[request.object_id]
            return DeviceIdentificationResponse(code, conformity, False, 0, ((request.object_id, value),))
        last = {1: 0x02, 2: 0x06, 3: 0xFF}[code]
        ids = sorted(object_id for object_id in objects if object_id <= last)
        # An object id the category does not hold restarts the stream at 0 (MB spec 6.21).
        start = request.object_id if request.object_id in ids else 0
        chosen = []
        size = 7
        more, next_id = False, 0
        for object_id in ids:
            if object_id < start:
                continue
            value = objects[object_id]
            if size + 2 + len(value) > MAX_PDU and chosen:
                more, next_id = True, object_id  # split: the client asks again from here
                break
            chosen.append((object_id, value))
            size += 2 + len(value)
        return DeviceIdentificationResponse(code, conformity, more, next_id, tuple(chosen))


# -- loading a data file (--data) --------------------------------------------------------

TABLES = ("coils", "discrete_inputs", "holding_registers", "input_registers")


def load_data(
    path: str, units: frozenset[int], listed_only: bool = False
) -> tuple[DataModel, dict[int, DataModel]]:
    """A template model and per-unit models from a JSON or TOML file (README, "Simulating a device").

    ``listed_only``: mark the addresses the file lists, as a sparse file does, whatever
    it says (diff compares those and no others)."""
    try:
        with open(path, "rb") as handle:
            raw = handle.read()
    except OSError as error:
        raise RequestError(f"cannot read data file {path}: {error.strerror or error}") from None
    try:
        if path.lower().endswith(".toml"):
            import tomllib

            data = tomllib.loads(raw.decode("utf-8"))
        else:
            import json

            data = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as error:
        raise RequestError(f"data file {path} is not valid {_kind(path)}: {error}") from None
    except RecursionError:  # json and tomllib parse arrays inside one another recursively
        raise RequestError(
            f"data file {path}: nested too deeply (arrays or tables inside one another)"
        ) from None
    if not isinstance(data, dict):
        raise RequestError(f"data file {path}: the top level must be a table of sections")
    template = DataModel()
    sparse = data.get("sparse", False)
    if not isinstance(sparse, bool):
        raise RequestError(f"data file {path}: sparse must be true or false")
    if sparse or listed_only:
        template.defined = {}  # only what the file lists exists; units.N add their own
    per_unit_sections = data.get("units", {})
    if not isinstance(per_unit_sections, dict):
        raise RequestError(f"data file {path}: 'units' must map unit ids to sections")
    complete = data.get("complete", True)  # mbtool dump marks a dump it did not finish
    if not isinstance(complete, bool):
        raise RequestError(f"data file {path}: complete must be true or false")
    top = {k: v for k, v in data.items() if k not in ("units", "sparse", "complete")}
    apply_data(template, top, path)
    unit_models = {}
    for key, section in per_unit_sections.items():
        unit = _int(key, f"{path}: units", 1, 255)
        if unit not in units:
            raise RequestError(f"data file {path}: unit {unit} is not among the units served")
        if not isinstance(section, dict):
            raise RequestError(f"data file {path}: units.{key} must be a table")
        model = template.copy()
        apply_data(model, section, f"{path}: units.{key}")
        unit_models[unit] = model
    return template, unit_models


def _kind(path: str) -> str:
    return "TOML" if path.lower().endswith(".toml") else "JSON"


def _int(value, where: str, low: int, high: int) -> int:
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, str):
        try:
            value = int(value.strip(), 0) if not value.strip().isdigit() else int(value.strip())
        except ValueError:
            raise RequestError(f"data file {where}: {value} is not a number") from None
    if not isinstance(value, int):
        raise RequestError(f"data file {where}: {value} is not a number")
    if not low <= value <= high:
        raise RequestError(f"data file {where}: {value} is out of range {low}..{high}")
    return value


def _bytes(value, where: str) -> bytes:
    if isinstance(value, str):
        return value.encode("utf-8")
    if isinstance(value, list):
        return bytes(_int(v, where, 0, 255) for v in value)
    raise RequestError(f"data file {where}: expected a string or a list of bytes")


def _fill(table, section, where: str, high: int, size: int, defined: bytearray | None) -> None:
    """ADDRESS = value, [values] or a run { value = V, count = N } into ``table``;
    ``defined`` (sparse) marks each address set."""
    if not isinstance(section, dict):
        raise RequestError(f"data file {where}: expected a table of ADDRESS = value(s)")
    for key, values in section.items():
        start = _int(key, f"{where}", 0, size - 1)
        if isinstance(values, dict):  # a run of one value, as mbtool dump writes long ones
            if set(values) != {"value", "count"}:
                raise RequestError(f"data file {where}.{key}: a run is {{ value = V, count = N }}")
            values = [values["value"]] * _int(values["count"], f"{where}.{key}.count", 1, size)
        values = values if isinstance(values, list) else [values]
        if start + len(values) > size:
            raise RequestError(f"data file {where}.{key}: {len(values)} values run past {size - 1}")
        for offset, value in enumerate(values):
            table[start + offset] = _int(value, f"{where}.{key}", 0, high)
        if defined is not None:
            defined[start : start + len(values)] = b"\x01" * len(values)


def apply_data(model: DataModel, data: dict, where: str) -> None:
    known = {*TABLES, "files", "exception_status", "diagnostic_register", "identity"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise RequestError(
            f"data file {where}: unknown section {unknown[0]} (expected one of {sorted(known)})"
        )
    for name in TABLES:
        if name in data:
            bits = name in ("coils", "discrete_inputs")
            _fill(
                getattr(model, name),
                data[name],
                f"{where}: {name}",
                1 if bits else 0xFFFF,
                TABLE_SIZE,
                model.defines(name, TABLE_SIZE),
            )
    files = data.get("files", {})
    if not isinstance(files, dict):
        raise RequestError(f"data file {where}: files must map file numbers to records")
    for key, section in files.items():
        number = _int(key, f"{where}: files", 1, 0xFFFF)
        _fill(
            model.file(number, create=True),
            section,
            f"{where}: files.{key}",
            0xFFFF,
            FILE_SIZE,
            model.defines(number, FILE_SIZE),
        )
    if "exception_status" in data:
        model.exception_status = _int(data["exception_status"], f"{where}: exception_status", 0, 0xFF)
    if "diagnostic_register" in data:
        model.diagnostic_register = _int(
            data["diagnostic_register"], f"{where}: diagnostic_register", 0, 0xFFFF
        )
    identity = data.get("identity", {})
    if not isinstance(identity, dict):
        raise RequestError(f"data file {where}: identity must be a table")
    for key, value in identity.items():
        here = f"{where}: identity.{key}"
        if key == "slave_id":
            model.slave_id = _int(value, here, 0, 0xFF)
        elif key == "run":
            if not isinstance(value, bool):
                raise RequestError(f"data file {here}: expected true or false")
            model.run_indicator = value
        elif key == "extra":
            model.slave_id_extra = _bytes(value, here)[: MAX_PDU - 4]
        elif key in OBJECT_KEYS:
            model.objects[OBJECT_KEYS[key]] = _object(value, here)
        elif key == "objects":
            if not isinstance(value, dict):
                raise RequestError(f"data file {here}: expected a table of OBJECT_ID = value")
            for object_key, object_value in value.items():
                object_id = _int(object_key, here, 0, 0xFF)
                model.objects[object_id] = _object(object_value, f"{here}.{object_key}")
        else:
            raise RequestError(f"data file {here}: unknown key")


def _object(value, where: str) -> bytes:
    data = _bytes(value, where)
    if len(data) > MAX_PDU - 9:
        raise RequestError(
            f"data file {where}: {len(data)} bytes do not fit one reply (at most {MAX_PDU - 9})"
        )
    return data
