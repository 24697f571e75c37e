"""The other function codes: FC 07, 11, 12, 17, 20-24 and 43/14 (spec §3, §5, §6).

FC 08 (diagnostics) has its own module, diagnostics.py.
"""

from __future__ import annotations

from functools import partial

import click

from mbtool.cli.options import NONFINITE_OPTION, VALUE_TYPES, device_command
from mbtool.cli.param_types import ADDRESS, COUNT, Choice, Number, parse_int
from mbtool.cli.results import Report, Result, Row
from mbtool.cli.session import execute, open_client, show
from mbtool.codec.pdu import printable, text_of
from mbtool.codec.record import replace
from mbtool.codec.values import (
    decode_values,
    parse_register,
    parse_registers,
    registers_needed,
    value_addresses,
)
from mbtool.errors import UsageError
from mbtool.words import counted

# --- FC 07 ---------------------------------------------------------------------------------


@device_command("read-exception-status")
def read_exception_status(connection, settings):
    """Read exception status (FC 07).

    Eight device-defined status bits, each ON or OFF (a serial-line function).
    On Modicon controllers they are coils 1-8 (484: 257-264, 884: 761-768).
    """
    from mbtool.codec.serial_line import ReadExceptionStatus  # noqa: PLC0415 - 0.7 ms: FC 07-17 only

    request = ReadExceptionStatus()
    reply = execute(connection, settings, request)
    rows = [Row("status", reply.status, f"0x{reply.status:02X}")]
    rows += [Row(f"bit{i}", bit, "ON" if bit else "OFF") for i, bit in enumerate(reply.bits)]
    data = {"status": reply.status, "bits": list(reply.bits)}
    show(connection, settings, Report(connection.unit, request.function_code, request.name, rows, data))


# --- FC 11 / 12 ---------------------------------------------------------------------------


def _status_text(status: int) -> str:
    return {0xFFFF: "busy", 0x0000: "idle"}.get(status, f"0x{status:04X} (neither busy nor idle)")


@device_command("event-counter")
def event_counter(connection, settings):
    """Get the comm event counter (FC 11).

    The status (busy or idle) and the count of successful messages.
    """
    from mbtool.codec.serial_line import GetCommEventCounter  # noqa: PLC0415 - 0.7 ms: FC 07-17 only

    request = GetCommEventCounter()
    reply = execute(connection, settings, request)
    rows = [Row("status", _status_text(reply.status)), Row("event_count", reply.event_count)]
    data = {"status": _status_text(reply.status), "busy": reply.busy, "event_count": reply.event_count}
    show(
        connection,
        settings,
        _with_warnings(Report(connection.unit, request.function_code, request.name, rows, data), reply),
    )


@device_command("event-log")
def event_log(connection, settings):
    """Get the comm event log (FC 12).

    Status, event and message counts, and each event byte (0 = newest) in words.
    """
    from mbtool.codec.serial_line import (  # noqa: PLC0415 - 0.7 ms: FC 07-17 only
        GetCommEventLog,
        describe_event,
    )

    request = GetCommEventLog()
    reply = execute(connection, settings, request)
    rows = [
        Row("status", _status_text(reply.status)),
        Row("event_count", reply.event_count),
        Row("message_count", reply.message_count),
    ]
    events = [{"byte": byte, "description": describe_event(byte)} for byte in reply.events]
    rows += [
        Row(f"event{i}", e["byte"], f"0x{e['byte']:02X} {e['description']}") for i, e in enumerate(events)
    ]
    data = {
        "status": _status_text(reply.status),
        "busy": reply.busy,
        "event_count": reply.event_count,
        "message_count": reply.message_count,
        "events": events,
    }
    show(
        connection,
        settings,
        _with_warnings(Report(connection.unit, request.function_code, request.name, rows, data), reply),
    )


def _with_warnings(report, reply):
    """What a strict reader noticed in the reply (e.g. a status word neither busy nor idle):
    a ``warning`` row, and a ``warnings`` list in JSON; stderr stays for the one error line."""
    warnings = list(getattr(reply, "warnings", ()))
    if not warnings:
        return report
    rows = report.rows + [Row("warning", text) for text in warnings]
    data = dict(report.data or {}, warnings=warnings)
    return replace(report, rows=rows, data=data)


# --- FC 17 ------------------------------------------------------------------------------------


@device_command("report-id")
def report_id(connection, settings):
    """Report server (slave) ID (FC 17).

    The id, the run indicator and the device's own bytes.  The extra bytes are shown in hex and as text; replies of Modicon 184/384,
    584 and 984 controllers are decoded field by field (status word, machine
    state, stop code).
    """
    from mbtool.codec.modicon import (  # noqa: PLC0415 - report-id only
        SLAVE_IDS,
        modicon_fields,
        modicon_layout,
    )
    from mbtool.codec.serial_line import ReportSlaveId  # noqa: PLC0415 - 0.7 ms: FC 07-17 only

    request = ReportSlaveId()
    reply = execute(connection, settings, request)
    layout = modicon_layout(reply.slave_id, reply.extra)
    run = "ON" if reply.run_indicator else "OFF"
    if reply.run_indicator_byte is not None:  # neither 00 nor FF: say neither, not ON
        run = f"unknown (byte {reply.run_indicator_byte:02X})"
    rows = [
        Row(
            "slave_id",
            reply.slave_id,
            f"{reply.slave_id}" + (f" (Modicon {SLAVE_IDS[reply.slave_id]})" if layout else ""),
        ),
        Row("run_indicator", run),
    ]
    data: dict = {
        "slave_id": reply.slave_id,
        "run_indicator": reply.run_indicator if reply.run_indicator_byte is None else None,
    }
    if layout:
        data["layout"] = f"Modicon {layout}"
        for name, value, text in modicon_fields(layout, reply.extra):
            rows.append(Row(name, value, text))
            data[name] = value
    extra_hex = reply.extra.hex(" ").upper()
    rows += [Row("extra_hex", extra_hex or "-"), Row("extra_text", printable(reply.extra) or "-")]
    data.update(extra_hex=extra_hex, extra_text=printable(reply.extra))
    show(
        connection,
        settings,
        _with_warnings(Report(connection.unit, request.function_code, request.name, rows, data), reply),
    )


# --- FC 20 / 21 --------------------------------------------------------------------------------


def _groups(tokens: tuple[str, ...]) -> list[list[str]]:
    """Split arguments at lone commas: the groups of one file-record request."""
    groups: list[list[str]] = [[]]
    for token in tokens:
        if token == ",":
            groups.append([])
        else:
            groups[-1].append(token)
    if any(not group for group in groups):
        raise UsageError("an empty group: put one ',' between groups, not at either end")
    return groups


@device_command("read-file-record")
@click.argument("groups", nargs=-1, required=True, metavar="FILE RECORD LENGTH [FILE RECORD LENGTH]...")
def read_file_record(connection, settings, groups):
    """Read file records (FC 20).

    LENGTH registers from RECORD (0..9999) of FILE (1..65535). Several groups go in one request: read-file-record 4 1 2 3 9 2.
    Output lines are FILE:RECORD VALUE.
    """
    from mbtool.codec.file_record import (  # noqa: PLC0415 - the file records only
        FileRecordRequest,
        ReadFileRecord,
    )

    numbers = [parse_int(token, "file, record or length") for token in groups if token != ","]
    if len(numbers) % 3:
        raise UsageError(f"give FILE RECORD LENGTH in threes, not {len(numbers)} numbers")
    parts = tuple(FileRecordRequest(*numbers[i : i + 3]) for i in range(0, len(numbers), 3))
    request = ReadFileRecord(parts)
    reply = execute(connection, settings, request)
    rows, data = [], []
    for part, values in zip(parts, reply.records, strict=True):
        rows += [Row(f"{part.file}:{part.record + i}", value) for i, value in enumerate(values)]
        data.append({"file": part.file, "record": part.record, "values": list(values)})
    show(
        connection,
        settings,
        Report(connection.unit, request.function_code, request.name, rows, {"groups": data}),
    )


@device_command("write-file-record")
@click.argument("groups", nargs=-1, required=True, metavar="FILE RECORD VALUE... [, FILE RECORD VALUE...]...")
def write_file_record(connection, settings, groups):
    """Write file records (FC 21).

    VALUEs from RECORD (0..9999) of FILE (1..65535). Separate several groups with a lone comma: write-file-record 4 7 0x6AF 0x4BE , 3 9 100.
    Each VALUE is -32768..65535 or 0x hex.
    """
    from mbtool.codec.file_record import FileRecord, WriteFileRecord  # noqa: PLC0415 - the file records only

    parts = []
    for group in _groups(groups):
        if len(group) < 3:
            raise UsageError(f"group {' '.join(group)} needs FILE RECORD and at least one VALUE")
        file, record = parse_int(group[0], "file number"), parse_int(group[1], "record number")
        parts.append(FileRecord(file, record, tuple(parse_register(text) for text in group[2:])))
    request = WriteFileRecord(tuple(parts))
    execute(connection, settings, request)
    rows = [Row(f"{p.file}:{p.record + i}", value) for p in parts for i, value in enumerate(p.values)]
    data = [{"file": p.file, "record": p.record, "values": list(p.values)} for p in parts]
    show(
        connection,
        settings,
        Report(connection.unit, request.function_code, request.name, rows, {"groups": data}),
    )


# --- FC 22 / 23 / 24 ------------------------------------------------------------------------------

MASK = Number(0, 0xFFFF, "mask")


@device_command("mask-write-register")
@click.argument("address", type=ADDRESS)
@click.argument("and_mask", type=MASK)
@click.argument("or_mask", type=MASK)
def mask_write_register(connection, settings, address, and_mask, or_mask):
    """Mask write register (FC 22).

    The register at ADDRESS becomes (current AND AND_MASK) OR (OR_MASK AND NOT
    AND_MASK). E.g. mask-write-register 4 0xF2 0x25 turns 0x12 into 0x17.
    """
    from mbtool.codec.data_access import (  # noqa: PLC0415 - 0.8 ms: FC 22-24 only
        MaskWriteRegister,
        mask_formula,
    )

    request = MaskWriteRegister(address, and_mask, or_mask)
    execute(connection, settings, request)
    rows = [
        Row("address", address),
        Row("and_mask", and_mask, f"0x{and_mask:04X}"),
        Row("or_mask", or_mask, f"0x{or_mask:04X}"),
        Row("result", mask_formula(and_mask, or_mask)),
    ]
    show(connection, settings, Report(connection.unit, request.function_code, request.name, rows))


@device_command("read-write-registers", types=VALUE_TYPES)
@click.argument("read_address", type=ADDRESS)
@click.argument("read_count", type=COUNT)
@click.argument("write_address", type=ADDRESS)
@click.argument("values", nargs=-1, required=True, metavar="VALUE...")
@NONFINITE_OPTION
def read_write_registers(
    connection, settings, read_address, read_count, write_address, values, allow_nonfinite, value_type, order
):
    """Read/write registers (FC 23).

    Write VALUEs at WRITE_ADDRESS, then read READ_COUNT from READ_ADDRESS. The device writes before it reads (spec). At most 121 registers written and
    125 read; with --type both sides count values of that type.
    """
    from mbtool.codec.data_access import ReadWriteMultipleRegisters  # noqa: PLC0415 - 0.8 ms: FC 22-24 only

    registers = parse_registers(values, value_type, order, allow_nonfinite)
    request = ReadWriteMultipleRegisters(
        read_address, registers_needed(value_type, read_count), write_address, tuple(registers)
    )
    reply = execute(connection, settings, request)
    result = Result(
        connection.unit,
        request.function_code,
        request.name,
        read_address,
        decode_values(reply.registers, value_type, order),
        value_type,
        list(reply.registers),
        extra={"written": {"address": write_address, "registers": registers}},
        addresses=value_addresses(value_type, read_address, len(reply.registers)),
    )
    show(connection, settings, result)


@device_command("fifo")
@click.argument("address", type=ADDRESS)
def fifo(connection, settings, address):
    """Read a FIFO queue (FC 24).

    The entries queued behind the pointer register at ADDRESS. Output: "count N", then INDEX VALUE lines, the oldest entry first; at most 31.
    """
    from mbtool.codec.data_access import ReadFifoQueue  # noqa: PLC0415 - 0.8 ms: FC 22-24 only

    request = ReadFifoQueue(address)
    reply = execute(connection, settings, request)
    rows = [Row("count", len(reply.registers))]
    rows += [Row(str(i), value) for i, value in enumerate(reply.registers)]
    data = {"address": address, "count": len(reply.registers), "values": list(reply.registers)}
    report = Report(
        connection.unit,
        request.function_code,
        request.name,
        rows,
        data,
        note=f"{counted(len(reply.registers), 'entry', 'entries')} queued at pointer address {address}",
    )
    show(connection, settings, report)


# --- FC 43 / 14 --------------------------------------------------------------------------------------

LEVELS = {"basic": 1, "regular": 2, "extended": 3}


@device_command("device-id")
@click.option(
    "--level",
    type=Choice(list(LEVELS)),
    default="basic",
    show_default=True,
    help="Objects to read: basic 0x00-0x02, regular up to 0x06, extended up to 0xFF.",
)
@click.option("--object", "object_id", type=Number(0, 255, "object id"), help="Read this one object only.")
def device_id(connection, settings, level, object_id):
    """Read device identification (FC 43/14).

    Vendor, product code, revision and more, by level or one object. Follows more-follows across requests until every object of the level is read.
    """
    from mbtool.codec.device_id import (  # noqa: PLC0415 - device-id only
        ReadDeviceIdentification,
        conformity_name,
        object_name,
    )

    objects: dict[int, bytes] = {}
    conformity = None
    follows = "" if object_id is not None else "any further request depends on the reply's more-follows"
    with open_client(connection, settings, ReadDeviceIdentification.name, then=follows) as client:
        if object_id is not None:
            request = ReadDeviceIdentification(4, object_id)
            reply = client.execute(connection.unit, request)
            conformity = reply.conformity_name
            objects.update(reply.objects)
        else:
            from mbtool.link.dump import read_identification  # noqa: PLC0415 - device-id only

            objects, conformity_code = read_identification(
                partial(client.execute, connection.unit), LEVELS[level]
            )
            conformity = conformity_name(conformity_code)
    rows = [Row(object_name(i), text_of(value)) for i, value in objects.items()]
    if not rows:
        rows = [Row("objects", "none: the device answered with no objects")]
    data = {
        "conformity": conformity,
        "objects": {object_name(i): text_of(value) for i, value in objects.items()},
    }
    show(
        connection,
        settings,
        Report(
            connection.unit, 0x2B, "Read Device Identification", rows, data, note=f"conformity: {conformity}"
        ),
    )
