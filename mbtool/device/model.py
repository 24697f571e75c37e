"""What a simulated device holds: its tables, files and identity, and each unit's counters and log.

Tables are a bytearray (bits) and array("H") (registers): no Python object
per item, so a one-shot ``-p sim://`` command pays microseconds for them.

What a master (or a data file) can make the device hold is bounded: a unit's
tables are shared with the template, and the other units, until something
writes to one (then that table is copied for it: 64 KB of bits, 128 KB of
registers), and a unit holds at most MAX_FILES files of FILE_SIZE registers.
So a unit costs at most 384 KB of tables and 320 KB of files, however many
requests it gets, and a read costs nothing.

The handlers of ``mbtool.device.handlers`` answer requests from here; the ``Device`` of
``mbtool.device.device`` keeps a ``Station`` for each unit it serves; ``mbtool.device.datafile``
fills a model from a data file (--data).
"""

from __future__ import annotations

from array import array
from collections import deque
from typing import Literal, overload

from mbtool.codec.errors import RequestError
from mbtool.codec.pdu import ExceptionCode

TABLE_SIZE = 0x10000  # every table spans the whole 16-bit address space (spec §1)
TABLES = ("coils", "discrete_inputs", "holding_registers", "input_registers")
FILE_SIZE = 10000  # records 0..9999 per file (spec §1, FC20/21)
# Files a unit holds (FC20/21), 20 KB each: a write that would make one more answers
# exception 02, as a device answers for a file it does not have.  File numbers run
# 1..65535 (spec §3); without a bound a master writing to each took a GB.
MAX_FILES = 16
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

# The diagnostic counters: FC08 sub-functions 0B..13 return one each (spec §4), in this order.
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
# Those of the bus, which every unit on it shares (Station.bus).
BUS_COUNTERS = ("bus_messages", "bus_comm_errors", "bus_char_overruns")

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
IDENTITY_FUNCTIONS = {0x11, 0x2B}  # FC 17 and FC 43, which a data file's identity may refuse


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
        # The FC17 run indicator byte: FF on, 00 off, or whatever else a dumped device sent;
        # None: ON (the handler says FF), so the device loads no codec.serial_line to start.
        self.run_indicator: int | None = None
        self.slave_id_extra = b"mbtool"
        self.objects: dict[int, bytes] = dict(DEFAULT_OBJECTS)  # FC43/14
        self.conformity: int | None = None  # FC43/14's conformity level; None: from the objects
        # FC 17 and FC 43 as a dumped device answered them: exception 01, no such function.
        self.refused: frozenset[int] = frozenset()
        # A sparse data file (README, "Simulating a device"): what it defines, per table name
        # and per file number, 1 for each address it lists.  None: every address exists.
        self.defined: dict[str | int, bytearray] | None = None
        self.complete = True  # False: a dump mbtool did not finish (complete = false in the file)
        # What this model shares with a copy (a table name, ("file", N), ("defined", key)):
        # copied for itself before its first write, so a copy costs nothing until written.
        self._shared: set = set()

    def copy(self) -> DataModel:
        """A model with the same contents; the tables, files and masks are shared by both
        until either writes to one (writable, writable_file, defines)."""
        other = DataModel.__new__(DataModel)
        shared = {*TABLES, *(("file", number) for number in self.files)}
        other.coils = self.coils
        other.discrete_inputs = self.discrete_inputs
        other.holding_registers = self.holding_registers
        other.input_registers = self.input_registers
        other.files = dict(self.files)
        other.exception_status = self.exception_status
        other.diagnostic_register = self.diagnostic_register
        other.slave_id = self.slave_id
        other.run_indicator = self.run_indicator
        other.slave_id_extra = self.slave_id_extra
        other.objects = dict(self.objects)
        if self.defined is None:
            other.defined = None
        else:
            other.defined = dict(self.defined)
            shared.update(("defined", key) for key in self.defined)
        other.complete = self.complete
        other.conformity = self.conformity
        other.refused = self.refused
        self._shared |= shared
        other._shared = set(shared)
        return other

    # The bit tables are bytes (one a bit), the register tables arrays of uint16.
    @overload
    def writable(self, name: Literal["coils", "discrete_inputs"]) -> bytearray: ...
    @overload
    def writable(self, name: Literal["holding_registers", "input_registers"]) -> array: ...
    @overload
    def writable(self, name: str) -> bytearray | array: ...
    def writable(self, name: str) -> bytearray | array:
        """The table ``name`` to write into: first made its own if it shares it."""
        if name in self._shared:
            self._shared.discard(name)
            setattr(self, name, getattr(self, name)[:])
        return getattr(self, name)

    def file(self, number: int) -> array | None:
        """File ``number`` to read, or None if it was never written (it reads as zeros)."""
        return self.files.get(number)

    def make_files(self, numbers) -> None:
        """Files ``numbers`` exist after this; exception 02 (and none made) if that would be
        more than MAX_FILES, as a device answers for a file it does not have."""
        new = set(numbers) - self.files.keys()
        if len(self.files) + len(new) > MAX_FILES:
            raise RequestError(
                f"{len(self.files) + len(new)} files: a unit holds at most {MAX_FILES}",
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
            )
        for number in new:
            self.files[number] = array("H", bytes(2 * FILE_SIZE))

    def writable_file(self, number: int) -> array:
        """File ``number`` (made by make_files) to write into: first made its own if it shares it."""
        if ("file", number) in self._shared:
            self._shared.discard(("file", number))
            self.files[number] = self.files[number][:]
        return self.files[number]

    def defines(self, key: str | int, size: int) -> bytearray | None:
        """The mask a sparse data file marks its addresses in (a table name or a file number),
        to write into; None when the model is not sparse."""
        if self.defined is None:
            return None
        mask = self.defined.get(key)
        if mask is None:
            mask = self.defined[key] = bytearray(size)
        elif ("defined", key) in self._shared:
            self._shared.discard(("defined", key))
            mask = self.defined[key] = mask[:]
        return mask

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


class Station:
    """One unit id: its tables, its diagnostic counters and its event log (spec §4, §5).

    ``bus``: the bus-level counters (BUS_COUNTERS), one dict shared by every station of a
    device: every node on the line sees every message (spec §4)."""

    def __init__(self, unit: int, model: DataModel, bus: dict[str, int]) -> None:
        self.unit = unit
        self.model = model
        self.bus = bus
        self.counters = dict.fromkeys(COUNTER_SUBS.values(), 0)
        self.event_count = 0  # FC11: successful completions, not counting FC11/FC12 polls
        self.events: deque[int] = deque(maxlen=MAX_EVENTS)  # newest first (appendleft)
        self.listen_only = False
        self.ascii_delimiter = 0x0A

    def count(self, name: str) -> None:
        self.counters[name] = (self.counters[name] + 1) & 0xFFFF

    def log(self, event: int) -> None:
        self.events.appendleft(event)

    def reported_counters(self) -> dict[str, int]:
        """The FC08 counters as the unit reports them: its own, and the bus's."""
        return {**self.counters, **{name: self.bus[name] for name in BUS_COUNTERS}}

    def clear_counters(self) -> None:
        """The communication event counters, the bus's too (FC08 sub 01 and 0A); not the
        diagnostic register."""
        for name in self.counters:
            self.counters[name] = 0
        self.event_count = 0
        for name in BUS_COUNTERS:
            self.bus[name] = 0
