"""Renderers: turn a result into table, plain, JSON or CSV text.  They never talk to a device.

The default follows the terminal (httpie's rule): a rich table when stdout is a
TTY, plain ``ADDRESS VALUE`` lines in a pipe.  rich is imported only when a
table is drawn: it costs tens of milliseconds a cron job should not pay.
"""

from __future__ import annotations

import math
import os
import stat
import sys
import time
from collections.abc import Sequence
from typing import TextIO

from mbtool.codec.errors import ChecksumError, FrameError, function_code_text
from mbtool.codec.framing import Framer
from mbtool.codec.record import record

FORMATS = ("table", "plain", "json", "csv")
MONITORING_FORMATS = ("influx", "prom")  # cli/metrics.py writes them, for the read commands


@record
class Result:
    """What a command learned (or wrote): values at addresses, and their context."""

    unit: int
    function: int
    name: str
    address: int
    values: list  # bits, or values of ``type``; {order: value} each with --order all
    type: str | None = None  # None for bits; a register type from codec.values otherwise
    registers: Sequence[int] | None = None  # the raw registers behind typed values, as read
    note: str = ""  # one line for the human, e.g. "broadcast: no device confirms"
    extra: dict | None = None  # more keys for JSON
    refs: list[str] | None = None  # Modicon references of the values (read REF): shown for addresses
    addresses: list[int] | None = None  # where each value starts; None: one a value from address

    def __init__(
        self,
        unit: int,
        function: int,
        name: str,
        address: int,
        values: list,
        type: str | None = None,
        registers: Sequence[int] | None = None,
        note: str = "",
        extra: dict | None = None,
        refs: list[str] | None = None,
        addresses: list[int] | None = None,
    ) -> None:
        # By hand: one a poll (codec/record.py).
        fields = self.__dict__
        fields["unit"] = unit
        fields["function"] = function
        fields["name"] = name
        fields["address"] = address
        fields["values"] = values
        fields["type"] = type
        fields["registers"] = registers
        fields["note"] = note
        fields["extra"] = extra
        fields["refs"] = refs
        # One value a register or a bit, from ``address`` on, unless the command says otherwise.
        fields["addresses"] = list(range(address, address + len(values))) if addresses is None else addresses

    @property
    def table(self) -> str:
        """The table a read of FC 01-04 read (coils, discrete, input, holding); else the
        function's name."""
        from mbtool.codec.tables import TABLE_OF_READ

        return TABLE_OF_READ.get(self.function, self.name)


def local_time(when: float | None = None) -> str:
    """Local time, ISO 8601 with milliseconds and UTC offset: what a log reader wants.

    Built from time.localtime, which knows the offset in force (a day-long poll crosses
    daylight saving time), at a third of datetime.astimezone's cost a poll.
    """
    when = time.time() if when is None else when
    second = int(when)
    if second != _SECOND[0]:  # one strftime a second, however fast the polls come
        local = time.localtime(second)
        offset = local.tm_gmtoff // 60
        sign = "-" if offset < 0 else "+"
        zone = f"{sign}{abs(offset) // 60:02d}:{abs(offset) % 60:02d}"
        _SECOND[:] = [second, time.strftime("%Y-%m-%dT%H:%M:%S", local), zone]
        if not _MILLISECONDS:  # made on first use: a one-shot command stamps nothing
            _MILLISECONDS.extend(f".{ms:03d}" for ms in range(1000))
    return _SECOND[1] + _MILLISECONDS[int((when - second) * 1000)] + _SECOND[2]


_SECOND: list = [None, "", ""]  # the last second stamped: (epoch second, its text, UTC offset)
_MILLISECONDS: list[str] = []  # ".000" to ".999": a poll looks its milliseconds up, not formats them


def error_json(message: str, code: int, **first: object) -> str:
    """The object -o json writes for a failure, one-shot or a poll's: {"error", "exit_code"}."""
    return to_json({**first, "error": message, "exit_code": code})


def wants_csv_header(out: TextIO, header: bool = True) -> bool:
    """A CSV header, unless --no-header (``header`` False, the run's settings), or unless the
    output is a regular file that already has content: cron's ``>> log.csv`` gets one
    header, not one a run."""
    if not header:
        return False
    try:
        fd = out.fileno()
        info = os.fstat(fd)
    except (AttributeError, OSError, ValueError):  # not a file (a StringIO, a closed stream)
        return True
    if not stat.S_ISREG(info.st_mode):
        return True
    out.flush()
    return info.st_size == 0 and os.lseek(fd, 0, os.SEEK_CUR) == 0


# The streams are looked up when called, not bound as defaults: cli.main may put a stdout in
# place of a closed one after this module is imported.
def default_format(stream: TextIO | None = None) -> str:
    return "table" if (stream or sys.stdout).isatty() else "plain"


def render(
    result: Result | Report | Points, fmt: str, out: TextIO | None = None, *, csv_header: bool = True
) -> None:
    """``csv_header``: the run's settings (False with --no-header)."""
    out = out or sys.stdout
    if isinstance(result, Points):
        renderers = {"table": _points_table, "plain": _points_plain, "json": _points_json, "csv": _points_csv}
    elif isinstance(result, Report):
        renderers = {"table": _report_table, "plain": _report_plain, "json": _report_json, "csv": _report_csv}
    else:
        renderers = {"table": _table, "plain": _plain, "json": _json, "csv": _csv}
    if fmt == "csv":
        renderers[fmt](result, out, csv_header)
    else:
        renderers[fmt](result, out)


def value_text(value: object) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, dict):  # --order all: the value in each word order
        return " ".join(f"{order}={value_text(each)}" for order, each in value.items())
    return str(value)


def change_parts(what: dict, old, new, unit: str = "") -> tuple[str, str, str]:
    """A value that differs (diff) or changed (--changes): what it is and both values as text.

    ``what`` names a map's point (name, ref) or an address (table, address); a value of
    None is an address a side does not have: "missing".  A point's bit is on or off, as
    read -m shows it."""
    point = "name" in what
    where = f"{what['name']} ({what['ref']})" if point else f"{what['table']} {what['address']}"

    def shown(value) -> str:
        if value is None:
            return "missing"
        return (point_text(value) if point else value_text(value)) + (f" {unit}" if unit else "")

    return where, shown(old), shown(new)


def change_line(what: dict, old, new, unit: str = "") -> str:
    """``holding 5: 5 -> 99``, ``setpoint (40006): 22.5 m3/h -> 23 m3/h``."""
    where, before, after = change_parts(what, old, new, unit)
    return f"{where}: {before} -> {after}"


def labels(result: Result) -> list:
    """What names each item: its reference when the user gave one (read 40108), else its address."""
    return result.refs if result.refs is not None else result.addresses


def by_order(result: Result) -> tuple[str, ...]:
    """The word orders of a --order all result (its values are {order: value}); () otherwise."""
    first = result.values[0] if result.values else None
    return tuple(first) if isinstance(first, dict) else ()


def csv_cells(result: Result) -> tuple[list[str], list[list[str]]]:
    """The CSV header and rows of a result: one column a word order with --order all."""
    orders = by_order(result)
    header = ["ref" if result.refs is not None else "address", *(orders or ["value"])]
    rows = [
        [str(label), *([value_text(value[o]) for o in orders] if orders else [value_text(value)])]
        for label, value in zip(labels(result), result.values, strict=True)
    ]
    return header, rows


def _plain(result: Result, out: TextIO) -> None:
    out.write(
        "".join(
            f"{label} {value_text(value)}\n"
            for label, value in zip(labels(result), result.values, strict=True)
        )
    )


def as_dict(result: Result) -> dict:
    data: dict = {
        "unit": result.unit,
        "function": result.function,
        "name": result.name,
        "address": result.address,
    }
    if result.type:
        data["type"] = result.type
    data["values"] = result.values
    data["addresses"] = result.addresses
    if result.refs is not None:
        data["refs"] = result.refs
    if result.registers is not None and result.type not in (None, "uint16"):
        data["registers"] = result.registers
    data.update(result.extra or {})
    return data


def to_json(value: object) -> str:
    """JSON text of plain data (dict, list, tuple, str, int, float, bool, None).

    Not the json module: importing it costs ~2 ms (its decoder too) that every
    one-shot ``-o json`` from cron would pay; strings are escaped by the same C
    function json itself uses.
    """
    from _json import encode_basestring_ascii

    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "null"  # NaN and infinities are not JSON; jq would choke on them
    if value is True:
        return "true"
    if value is False:
        return "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return encode_basestring_ascii(value)
    if isinstance(value, dict):
        return (
            "{"
            + ", ".join(f"{encode_basestring_ascii(str(k))}: {to_json(v)}" for k, v in value.items())
            + "}"
        )
    if isinstance(value, list | tuple):
        return "[" + ", ".join(to_json(item) for item in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def _json(result: Result, out: TextIO) -> None:
    out.write(to_json(as_dict(result)) + "\n")


def _csv(result: Result, out: TextIO, wanted: bool) -> None:
    import csv

    writer = csv.writer(out, lineterminator="\n")
    header, rows = csv_cells(result)
    if wants_csv_header(out, wanted):
        writer.writerow(header)
    writer.writerows(rows)


def _table(result: Result, out: TextIO) -> None:
    from rich.console import Console
    from rich.table import Table

    bits = result.type is None
    orders = by_order(result)
    table = Table()
    if result.refs is not None:
        table.add_column("Ref", justify="right")
    if result.refs is None or not orders:
        table.add_column("Address", justify="right")
    for heading in orders or ["Value"]:
        table.add_column(heading, justify="right", overflow="fold")  # a value is never cut short
    plain_registers = result.type == "uint16"
    if plain_registers:
        table.add_column("Hex", justify="right")
    typed_registers = not bits and not plain_registers and result.registers is not None
    if typed_registers:
        from mbtool.codec.values import TYPES

        width = TYPES[result.type].registers
        table.add_column("Registers", justify="right")
    refs = result.refs if result.refs is not None else [None] * len(result.values)
    for ref, address, value in zip(refs, result.addresses, result.values, strict=True):
        cells = [] if ref is None else [ref]
        if ref is None or not orders:
            cells.append(str(address))
        if bits:
            cells.append("[green]ON[/]" if value else "[dim]OFF[/]")
        elif plain_registers:
            cells += [str(value), f"0x{value:04X}"]
        else:
            cells += [value_text(value[o]) for o in orders] if orders else [value_text(value)]
        if typed_registers:
            # The words behind each value: when a float looks wrong, they show the word order.
            start = address - result.address
            words = result.registers[start : start + (width or len(result.registers))]
            cells.append(" ".join(f"{w:04X}" for w in words))
        table.add_row(*cells)
    console = Console(file=out) if out is not sys.stdout else Console()
    console.print(
        f"[bold]{result.name}[/] · {function_code_text(result.function)} · unit {result.unit}",
        highlight=False,
    )
    console.print(table)
    if result.note:
        console.print(result.note, style="dim")


# --- a register map's points: name, value, unit ------------------------------------------


@record
class PointRow:
    """One point of a register map as read: ``value`` in engineering units (or its enum
    label, or on/off), ``raw`` the registers (or bits) it came from."""

    name: str
    value: object
    unit: str
    ref: str
    raw: tuple
    bits: bool  # a coil or discrete input: raw holds bits, not registers
    description: str = ""
    number: int | float | None = None  # the number behind the value (Point.number_of)
    no_label: bool = False  # a value the point's enum does not label (Point.no_label)

    @property
    def shown(self) -> str:
        return point_text(self.value) + (" (no label)" if self.no_label else "")


def point_text(value: object) -> str:
    """A map's point's value as text: a bit is on or off."""
    if isinstance(value, bool):
        return "on" if value else "off"
    return value_text(value)


@record
class PointFailure:
    """A point of a map the device refused: its name, ref and the device's answer."""

    name: str
    ref: str
    error: str


@record
class Points:
    """What ``read -m MAP`` learned.  Plain: ``NAME VALUE UNIT`` lines; JSON: the unit id,
    the map, and each point's name, value, unit, ref and raw registers; CSV: a row a point.
    The points the device refused (a partial read) are in ``failed``: in JSON and the table,
    and on stderr; plain and CSV lines are values only."""

    unit: int
    source: str  # the map file
    rows: list[PointRow]
    note: str = ""  # one line for the human, e.g. "broadcast: no device confirms"
    failed: list[PointFailure] = ()


POINT_CSV_HEADER = ["name", "value", "unit", "ref", "registers"]


def point_line(row: PointRow) -> str:
    return f"{row.name} {row.shown} {row.unit}".rstrip()


def point_cells(row: PointRow) -> list[str]:
    raw = " ".join(value_text(item) for item in row.raw)
    return [row.name, row.shown, row.unit, row.ref, raw]


def points_dict(points: Points) -> dict:
    return {
        "unit": points.unit,
        "map": points.source,
        "points": [
            {
                "name": row.name,
                "value": row.value,
                "unit": row.unit,
                "ref": row.ref,
                "bits" if row.bits else "registers": list(row.raw),
            }
            for row in points.rows
        ],
        **(
            {"failed": [{"name": f.name, "ref": f.ref, "error": f.error} for f in points.failed]}
            if points.failed
            else {}
        ),
    }


def points_table(points: Points, heading: str = ""):
    """The rich table of a map read (its heading above it, as polling draws it too)."""
    from rich.markup import escape
    from rich.table import Table

    described = any(row.description for row in points.rows)
    table = Table()
    for column, justify in (("Name", "left"), ("Value", "right"), ("Unit", "left"), ("Ref", "right")):
        table.add_column(column, justify=justify)
    table.add_column("Raw", justify="right")
    if described:
        table.add_column("Description")
    for row in points.rows:
        raw = " ".join(value_text(b) if row.bits else f"{b:04X}" for b in row.raw)
        cells = [escape(row.name), escape(row.shown), escape(row.unit), row.ref, raw]
        if described:
            cells.append(escape(row.description))
        table.add_row(*cells)
    for failure in points.failed:  # refused by the device: the answer where the value would be
        table.add_row(escape(failure.name), f"[red]{escape(failure.error)}[/]", "", failure.ref, "")
    return table


def points_heading(points: Points) -> str:
    return f"{points.source} · unit {points.unit}"


def _points_table(points: Points, out: TextIO) -> None:
    from rich.console import Console
    from rich.markup import escape

    console = Console(file=out) if out is not sys.stdout else Console()
    console.print(f"[bold]{escape(points_heading(points))}[/]", highlight=False)
    console.print(points_table(points))
    if points.note:
        console.print(escape(points.note), style="dim")


def _points_plain(points: Points, out: TextIO) -> None:
    out.write("".join(point_line(row) + "\n" for row in points.rows))


def _points_json(points: Points, out: TextIO) -> None:
    out.write(to_json(points_dict(points)) + "\n")


def _points_csv(points: Points, out: TextIO, wanted: bool) -> None:
    import csv

    writer = csv.writer(out, lineterminator="\n")
    if wants_csv_header(out, wanted):
        writer.writerow(POINT_CSV_HEADER)
    writer.writerows(point_cells(row) for row in points.rows)


# --- structured results: fields, counters, event lists, decoded frames -----------------


@record
class Row:
    """One named item of a Report.

    ``name`` is one token (a script splits the plain line at the first space);
    ``value`` is plain data for JSON; ``text`` is how a person reads it (default:
    the value); ``raw`` the bytes on the wire it came from (offline decoding).
    """

    name: str
    value: object
    text: str | None = None
    raw: bytes | None = None

    @property
    def shown(self) -> str:
        return value_text(self.value) if self.text is None else self.text


@record
class Report:
    """What a command learned that is not a run of addressed values: named rows.

    Plain: one ``NAME VALUE`` line per row.  JSON: ``unit``, ``function``, ``name``,
    then ``data`` (default: each row's name and value).  CSV: ``name,value`` rows
    (plus ``bytes`` when rows carry them).  Table: one rich table.
    """

    unit: int | None
    function: int | None
    name: str
    rows: list[Row]
    data: dict | None = None
    note: str = ""
    title: str = ""  # the table's heading; default name, function code and unit
    header: bool = True  # CSV header (off for the second and later of several reports)


def report_dict(report: Report) -> dict:
    head: dict = {"unit": report.unit, "function": report.function, "name": report.name}
    body = report.data if report.data is not None else {row.name: row.value for row in report.rows}
    return {**head, **body}


def _report_plain(report: Report, out: TextIO) -> None:
    out.write("".join(f"{row.name} {row.shown}\n" for row in report.rows))


def _report_json(report: Report, out: TextIO) -> None:
    out.write(to_json(report_dict(report)) + "\n")


def _report_csv(report: Report, out: TextIO, wanted: bool) -> None:
    import csv

    writer = csv.writer(out, lineterminator="\n")
    with_raw = any(row.raw is not None for row in report.rows)
    if report.header and wants_csv_header(out, wanted):
        writer.writerow(["name", "value", "bytes"] if with_raw else ["name", "value"])
    for row in report.rows:
        cells = [row.name, row.shown]
        if with_raw:
            cells.append("" if row.raw is None else row.raw.hex(" ").upper())
        writer.writerow(cells)


def _report_table(report: Report, out: TextIO) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    with_raw = any(row.raw is not None for row in report.rows)
    table = Table()
    table.add_column("Field")
    if with_raw:
        table.add_column("Bytes")
    table.add_column("Value")
    for row in report.rows:
        cells = [row.name.replace("_", " ")]
        if with_raw:
            cells.append("" if row.raw is None else row.raw.hex(" ").upper())
        cells.append(escape(row.shown))
        table.add_row(*cells)
    console = Console(file=out) if out is not sys.stdout else Console()
    title = report.title
    if not title:
        title = f"[bold]{escape(report.name)}[/]"
        if report.function is not None:
            title += f" · {function_code_text(report.function)}"
        if report.unit is not None:
            title += f" · unit {report.unit}"
    console.print(title, highlight=False)
    console.print(table)
    if report.note:
        console.print(escape(report.note), style="dim")


class HexTrace:
    """``--hex``: every frame sent and received, in hex on stderr, its checksum judged."""

    def __init__(self, framer: Framer, out: TextIO | None = None) -> None:
        self.framer = framer
        self.out = out or sys.stderr

    def sent(self, adu: bytes) -> None:
        self._line("TX", adu, self.framer.check(adu))

    def received(self, adu: bytes, note: str = "") -> None:
        verdict = self.framer.check(adu)
        self._line("RX", adu, f"{verdict}; {note}" if note else verdict)

    def rejected(self, data: bytes, error: FrameError) -> None:
        # A whole frame with a bad checksum is judged like any frame; other bytes say why not.
        verdict = self.framer.check(data) if isinstance(error, ChecksumError) else f"rejected: {error}"
        self._line("RX", data, verdict)

    def _line(self, direction: str, data: bytes, verdict: str) -> None:
        self.out.write(f"{direction} {shown_frame(data)}  {verdict}\n")
        self.out.flush()


def shown_frame(data: bytes) -> str:
    """A frame as the traces show it: hex pairs, or an ASCII frame's own text."""
    return data.hex(" ").upper() if not data.startswith(b":") else data.decode("ascii", "replace").strip()
