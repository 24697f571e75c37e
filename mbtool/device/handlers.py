"""The function handlers of the simulated device: a request (decoded by the codec) in, its reply out.

One function a function code, grouped by the codec's families (``codec.data_access``,
``file_record``, ``serial_line``, ``device_id``), each ``handler(station, request)`` with the
unit's ``Station`` (``mbtool.device.model``); ``HANDLERS`` lists them by function code.  A
handler raises ``RequestError`` for an exception reply and returns None when no reply is
due.  ``mbtool.device.device.Device`` chooses the station and does the bookkeeping.

The tables' replies (``codec.data_access``, which every read loads) are imported at the top; the
other families' where they are used, so a one-shot ``sim://`` read loads no codec module it
does not need.
"""

from __future__ import annotations

import struct
from array import array

from mbtool.codec.data_access import (
    MAX_FIFO_COUNT,
    BitsResponse,
    ReadFifoQueueResponse,
    RegistersResponse,
    WriteMultipleResponse,
)
from mbtool.codec.errors import RequestError
from mbtool.codec.pdu import ExceptionCode
from mbtool.device.model import (
    COUNTER_SUBS,
    EVENT_LISTEN_ONLY,
    EVENT_RESTART,
    MAX_PDU,
    TABLE_SIZE,
    DataModel,
    Station,
)

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

# The function codes that change data (spec §1's write column, and FC21 for files):
# a read-only device (serve --read-only) answers them exception 01, a function it does not do.
WRITE_FUNCTIONS = frozenset({0x05, 0x06, 0x0F, 0x10, 0x15, 0x16, 0x17})
# The FC08 sub-functions that change the device's state, refused alike (spec §4): restart
# (it also clears the counters), the ASCII delimiter, listen-only (which would silence the
# device for every master), clear counters and the diagnostic register, clear overrun.
# Sub 15 changes it only with 0004, clear the statistics.
STATE_SUBS = frozenset(
    {SUB_RESTART, SUB_ASCII_DELIMITER, SUB_LISTEN_ONLY, SUB_CLEAR_COUNTERS, SUB_CLEAR_OVERRUN}
)
MODBUS_PLUS_CLEAR = b"\x00\x04"


def changes_state(pdu: bytes) -> bool:
    """Does this request change the device's data or state (what serve --read-only refuses)?

    By function code and sub-function alone, before the request's own checks: a device
    without the function answers 01 to any form of it."""
    code = pdu[0] if pdu else 0
    if code in WRITE_FUNCTIONS:
        return True
    if code != 0x08 or len(pdu) < 3:
        return False
    sub = int.from_bytes(pdu[1:3], "big")
    return sub in STATE_SUBS or (sub == SUB_MODBUS_PLUS and pdu[3:5] == MODBUS_PLUS_CLEAR)


# -- FC 01-06, 15, 16, 22, 23, 24: the tables ------------------------------------


def _read_bits(model: DataModel, request, name: str):
    model.require(name, request.address, request.count)
    table = getattr(model, name)
    bits = tuple(bool(b) for b in table[request.address : request.address + request.count])
    return BitsResponse(request.function_code, bits)


def _read_registers(model: DataModel, request, name: str):
    model.require(name, request.address, request.count)
    table = getattr(model, name)
    return RegistersResponse(
        request.function_code, tuple(table[request.address : request.address + request.count])
    )


def _write_single_coil(station: Station, request):
    station.model.require("coils", request.address, 1)
    station.model.writable("coils")[request.address] = request.on
    return request


def _write_single_register(station: Station, request):
    station.model.require("holding_registers", request.address, 1)
    station.model.writable("holding_registers")[request.address] = request.value
    return request


def _write_multiple_coils(station: Station, request):
    station.model.require("coils", request.address, len(request.values))
    end = request.address + len(request.values)
    station.model.writable("coils")[request.address : end] = bytes(request.values)
    return WriteMultipleResponse(request.function_code, request.address, len(request.values))


def _write_multiple_registers(station: Station, request):
    station.model.require("holding_registers", request.address, len(request.values))
    end = request.address + len(request.values)
    station.model.writable("holding_registers")[request.address : end] = array("H", request.values)
    return WriteMultipleResponse(request.function_code, request.address, len(request.values))


def _mask_write_register(station: Station, request):
    station.model.require("holding_registers", request.address, 1)
    table = station.model.writable("holding_registers")
    table[request.address] = request.result(table[request.address])
    return request


def _read_write_registers(station: Station, request):
    """FC23: the write is done before the read (spec §3), once both ranges are known to exist."""
    model = station.model
    model.require("holding_registers", request.write_address, len(request.values))
    model.require("holding_registers", request.read_address, request.read_count)
    table = model.writable("holding_registers")
    table[request.write_address : request.write_address + len(request.values)] = array("H", request.values)
    end = request.read_address + request.read_count
    return RegistersResponse(request.function_code, tuple(table[request.read_address : end]))


def _read_fifo_queue(station: Station, request):
    """FC24: the FIFO pointer register holds the count, the entries follow it (README)."""
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


def _read_file_record(station: Station, request):
    from mbtool.codec.file_record import ReadFileRecordResponse  # noqa: PLC0415 - FC 20 only

    for group in request.groups:
        station.model.require(group.file, group.record, group.length)
    records = []
    for group in request.groups:
        values = station.model.file(group.file)
        if values is None:
            records.append((0,) * group.length)  # a file never written reads as zeros
        else:
            records.append(tuple(values[group.record : group.record + group.length]))
    return ReadFileRecordResponse(tuple(records))


def _write_file_record(station: Station, request):
    model = station.model
    for group in request.groups:  # every group exists before any is written
        model.require(group.file, group.record, len(group.values))
    model.make_files(group.file for group in request.groups)
    for group in request.groups:
        values = model.writable_file(group.file)
        values[group.record : group.record + len(group.values)] = array("H", group.values)
    return request  # the reply is an echo (spec §3)


# -- FC 07, 08, 11, 12, 17: the serial line ------------------------------------------


def _read_exception_status(station: Station, request):
    from mbtool.codec.serial_line import ExceptionStatusResponse  # noqa: PLC0415 - FC 07 only

    return ExceptionStatusResponse(station.model.exception_status & 0xFF)


def _diagnostics(station: Station, request):
    from mbtool.codec.serial_line import DiagnosticsResponse  # noqa: PLC0415 - FC 08 only

    sub, data = int(request.sub_function), request.data
    if sub == SUB_QUERY:
        return DiagnosticsResponse(sub, data)
    zero = data == b"\x00\x00"
    if sub == SUB_RESTART:
        if data not in RESTART_DATA:
            raise RequestError("restart data is neither 0000 nor FF00")
        restart(station, data)
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
        station.clear_counters()
        station.model.diagnostic_register = 0  # sub 0A alone clears it too (spec §4)
        return DiagnosticsResponse(sub, data)
    if sub == SUB_CLEAR_OVERRUN:
        station.bus["bus_char_overruns"] = 0
        return DiagnosticsResponse(sub, data)
    if sub == SUB_DIAG_REGISTER:
        value = station.model.diagnostic_register
    else:
        value = station.reported_counters()[COUNTER_SUBS[sub]]
    return DiagnosticsResponse(sub, struct.pack(">H", value))


def restart(station: Station, data: bytes) -> None:
    """Sub 01: leave listen-only, clear the communication event counters (and the log with
    FF00), log a restart.  The diagnostic register stays: only sub 0A clears it (spec §4)."""
    station.listen_only = False
    station.clear_counters()
    if data == b"\xff\x00":
        station.events.clear()
    station.log(EVENT_RESTART)


def _comm_event_counter(station: Station, request):
    from mbtool.codec.serial_line import CommEventCounterResponse  # noqa: PLC0415 - FC 11 only

    return CommEventCounterResponse(0x0000, station.event_count)


def _comm_event_log(station: Station, request):
    from mbtool.codec.serial_line import CommEventLogResponse  # noqa: PLC0415 - FC 12 only

    return CommEventLogResponse(
        0x0000, station.event_count, station.bus["bus_messages"], bytes(station.events)
    )


def _report_slave_id(station: Station, request):
    from mbtool.codec.serial_line import RUN_OFF, RUN_ON, ReportSlaveIdResponse  # noqa: PLC0415 - FC 17 only

    model = station.model
    _unless_refused(model, request)
    slave_id = station.unit if model.slave_id is None else model.slave_id
    run = RUN_ON if model.run_indicator is None else model.run_indicator
    return ReportSlaveIdResponse(
        slave_id & 0xFF,
        run != RUN_OFF,
        model.slave_id_extra,
        run_indicator_byte=None if run in (RUN_ON, RUN_OFF) else run,
    )


# -- FC 43 / MEI 14: device identification ----------------------------------------------


def _read_device_identification(station: Station, request):
    """FC43/14: stream access 1-3 from the object asked for, 4 one object (spec §3)."""
    from mbtool.codec.device_id import DeviceIdentificationResponse  # noqa: PLC0415 - FC 43 only

    _unless_refused(station.model, request)
    objects = station.model.objects
    conformity = station.model.conformity
    if conformity is None:
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
    chosen: list[tuple[int, bytes]] = []
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


def _unless_refused(model: DataModel, request) -> None:
    """A dumped device's "no such function" to FC 17 or FC 43, given again (identity.refused)."""
    if request.function_code in model.refused:
        raise RequestError(
            f"the device this copies has no FC {request.function_code}", ExceptionCode.ILLEGAL_FUNCTION
        )


# The handler of each function code the device does; any other is answered exception 01.
HANDLERS = {
    0x01: lambda station, request: _read_bits(station.model, request, "coils"),
    0x02: lambda station, request: _read_bits(station.model, request, "discrete_inputs"),
    0x03: lambda station, request: _read_registers(station.model, request, "holding_registers"),
    0x04: lambda station, request: _read_registers(station.model, request, "input_registers"),
    0x05: _write_single_coil,
    0x06: _write_single_register,
    0x07: _read_exception_status,
    0x08: _diagnostics,
    0x0B: _comm_event_counter,
    0x0C: _comm_event_log,
    0x0F: _write_multiple_coils,
    0x10: _write_multiple_registers,
    0x11: _report_slave_id,
    0x14: _read_file_record,
    0x15: _write_file_record,
    0x16: _mask_write_register,
    0x17: _read_write_registers,
    0x18: _read_fifo_queue,
    0x2B: _read_device_identification,
}
