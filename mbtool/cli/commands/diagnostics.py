"""FC 08 Diagnostics: every sub-function of spec §4 by name or number, and all counters at once."""

from __future__ import annotations

import sys

import click

from mbtool.cli.options import device_command
from mbtool.cli.param_types import Choice, parse_int
from mbtool.cli.results import Report, Row
from mbtool.cli.session import execute, open_client, show
from mbtool.codec.describe import parse_hex
from mbtool.codec.errors import MismatchError, ModbusException
from mbtool.codec.framing import is_broadcast
from mbtool.codec.modicon import MODBUS_PLUS_WORDS, diagnostic_register_bits
from mbtool.codec.raw import RawRequest
from mbtool.codec.serial_line import (
    DEFAULT_QUERY_DATA,
    ECHO_SUB_FUNCTIONS,
    SUB_FUNCTION_NAMES,
    Diagnostics,
    sub_function_number,
)
from mbtool.errors import NoResponse, UsageError
from mbtool.link.connection import framer_name

# command-line name -> sub-function (spec §4)
SUB_FUNCTIONS = {name: code for code, name in SUB_FUNCTION_NAMES.items()}
NAMES = {code: name for name, code in SUB_FUNCTIONS.items()}
COUNTERS = tuple(range(0x0B, 0x13))  # bus message .. bus character overrun: every controller family's set


def _sub_function(text: str) -> int:
    if text.lower() in SUB_FUNCTIONS:
        return SUB_FUNCTIONS[text.lower()]
    try:
        number = parse_int(text, "sub-function")
    except UsageError:
        raise UsageError(
            f"unknown sub-function {text}: use counters, a number, or one of {', '.join(SUB_FUNCTIONS)}"
        ) from None
    if not 0 <= number <= 0xFFFF:
        raise UsageError(f"sub-function {number} is out of range 0..65535")
    return number


def _data(sub: int, text: str | None, clear_log: bool) -> bytes:
    if sub == 0x01:
        if text is not None:
            raise UsageError("restart-comms takes no DATA: use --clear-log to also clear the event log")
        return b"\xff\x00" if clear_log else b"\x00\x00"
    if clear_log:
        raise UsageError("--clear-log belongs to restart-comms")
    if sub == 0x03:
        # CHAR 00: the new end-of-frame character replacing LF (spec §4).
        if text is None:
            raise UsageError("change-ascii-delimiter needs the new delimiter: a character or 0xNN")
        char = ord(text) if len(text) == 1 else parse_int(text, "delimiter")
        if not 0 <= char <= 0xFF:
            raise UsageError(f"delimiter {char} is not a byte")
        return bytes([char, 0])
    if sub == 0x15 and text is not None and text.lower() in ("get", "clear"):
        return b"\x00\x03" if text.lower() == "get" else b"\x00\x04"
    if text is None:
        if sub == 0x00:
            return DEFAULT_QUERY_DATA
        return b"\x00\x03" if sub == 0x15 else b"\x00\x00"
    data = parse_hex(text[2:] if text.lower().startswith("0x") else text)
    if sub != 0x00 and len(data) != 2:
        raise UsageError(f"DATA for sub-function {sub:02X} is 2 bytes (4 hex digits), not {len(data)}")
    return data


@device_command("diag")
@click.argument(
    "sub_function",
    metavar="SUBFUNCTION",
    shell_complete=lambda ctx, param, incomplete: [
        name for name in ("counters", *SUB_FUNCTIONS) if name.startswith(incomplete.lower())
    ],
)
@click.argument("data", required=False)
@click.option("--clear-log", is_flag=True, help="restart-comms: also clear the event log (data FF00).")
@click.option(
    "--controller",
    type=Choice(["184/384", "484", "584/984", "884"]),
    help="diagnostic-register: name the bits as this Modicon family does.",
)
def diag(connection, settings, sub_function, data, clear_log, controller):
    """Diagnostics (FC 08, serial line). SUBFUNCTION by name or number, DATA in hex.

    Names: return-query-data [HEX] (checks the echo), restart-comms [--clear-log],
    diagnostic-register [--controller], change-ascii-delimiter CHAR, force-listen-only
    (no reply), clear-counters, bus-message-count, bus-comm-error-count,
    bus-exception-count, slave-message-count, slave-no-response-count, slave-nak-count,
    slave-busy-count, bus-char-overrun-count, iop-overrun-count, clear-overrun,
    modbus-plus-stats [get|clear]; "counters" reads every counter in one table.
    """
    if is_broadcast(connection.unit, framer_name(connection)):
        raise UsageError("unit 0 is broadcast, which only writes may use; diag needs a unit 1..255")
    if sub_function.lower() == "counters":
        if data is not None or clear_log:
            raise UsageError("diag counters takes no DATA")
        report = _counters(connection, settings)
    else:
        sub = _sub_function(sub_function)
        report = _one(connection, settings, sub, _data(sub, data, clear_log), controller)
    show(connection, settings, report)


def _one(connection, settings, sub: int, data: bytes, controller: str | None):
    request = Diagnostics(sub, data)
    name = NAMES.get(sub, f"sub-function {sub_function_number(sub)}")
    title = f"Diagnostics: {name}"
    rows = [Row("sub_function", sub, f"{sub_function_number(sub)} {name}")]
    if sub == 0x00:
        # Our own echo check, to say "matched" or show both sides rather than only fail.

        reply = execute(connection, settings, RawRequest(request.encode()))
        echoed = bytes(reply.pdu[3:])
        matched = reply.pdu[:3] == request.encode()[:3] and echoed == data
        rows += [
            Row("sent", data.hex(" ").upper()),
            Row("received", echoed.hex(" ").upper()),
            Row("echo", matched, "matched" if matched else "MISMATCH"),
        ]
        if not matched:
            show(connection, settings, Report(connection.unit, 8, title, rows))
            raise MismatchError(
                f"return-query-data echo {echoed.hex(' ').upper()} differs from {data.hex(' ').upper()}"
            )
        return Report(connection.unit, 8, title, rows)
    try:
        reply = execute(connection, settings, request)
    except NoResponse as silence:
        if sub == 0x01:
            # Spec §4: a device in listen-only mode restarts without answering.
            raise NoResponse(
                f"{silence}; a device in listen-only mode restarts on restart-comms without a reply"
            ) from None
        raise
    if not request.expects_response and reply is None:
        rows.append(
            Row(
                "reply",
                f"none within {connection.timeout:g} s, as expected: the device is now in listen-only "
                "mode (restart-comms ends it)",
            )
        )
        return Report(connection.unit, 8, title, rows)
    if not request.expects_response:
        # pymodbus 3.16 answers 08 0004 and stays online; libmodbus and the spec send nothing.
        print(
            "mbtool: warning: the device answered force-listen-only, which the spec leaves"
            " unanswered: it may not be in listen-only mode",
            file=sys.stderr,
        )
        rows.append(Row("reply", f"answered: {reply.encode().hex(' ').upper()}"))
        return Report(connection.unit, 8, title, rows)
    if sub == 0x02:
        rows += _register_rows(reply.value, controller)
    elif sub in COUNTERS or sub == 0x13:
        rows.append(Row(name.replace("-", "_"), reply.value))
    elif sub == 0x15 and reply.statistics is not None:
        rows += _statistics_rows(reply.statistics)
    else:
        rows.append(Row("data", reply.data.hex(" ").upper()))
        if sub in ECHO_SUB_FUNCTIONS or sub == 0x15:
            rows.append(Row("echo", True, "matched"))  # Diagnostics.check_response refused any other
    return Report(connection.unit, 8, title, rows)


def _statistics_rows(words: tuple[int, ...]):
    """Modbus Plus statistics, each word named as seed 002 does; byte pairs shown as LO/HI."""
    rows = []
    for i, word in enumerate(words):
        name = MODBUS_PLUS_WORDS[i] if i < len(MODBUS_PLUS_WORDS) else "not named in seed 002"
        if name.startswith("LO: "):
            text = f"LO {word & 0xFF}, HI {word >> 8} ({name})"
        else:
            text = f"{word} (0x{word:04X}) {name}"
        rows.append(Row(f"word{i}", word, text))
    return rows


def _register_rows(value: int, controller: str | None):
    rows = [Row("diagnostic_register", value, f"0x{value:04X}")]
    if controller:
        found = diagnostic_register_bits(value, controller)
        rows += [Row(f"bit{bit}", True, text) for bit, text in found]
        if not found:
            rows.append(Row("bits", "none set"))
    else:
        rows.append(Row("bits", " ".join(str(b) for b in range(16) if value >> b & 1) or "none set"))
    return rows


def _counters(connection, settings):
    rows, answered, refused = [], 0, None
    data: dict = {}  # counter name -> its count, or the device's refusal
    with open_client(connection, settings, "diag counters") as client:
        if settings.dry_run:
            # Every request is known in advance: show them all, then stop as a dry run does.
            for sub in COUNTERS:
                client.show(connection.unit, Diagnostics(sub))
            client.finish(connection.unit)
        for sub in COUNTERS:
            key = NAMES[sub].replace("-", "_")
            try:
                reply = client.execute(connection.unit, Diagnostics(sub))
            except ModbusException as error:
                refused = error
                rows.append(
                    Row(key, None, f"not supported: exception {error.exception_code:02X} {error.name}")
                )
                data[key] = None
                continue
            answered += 1
            rows.append(Row(key, reply.value))
            data[key] = reply.value
    if not answered and refused is not None:
        raise refused  # not one counter: the device does not do FC08 counters at all
    return Report(connection.unit, 8, "Diagnostics: counters", rows, data)
