"""Renderers: turn a result (cli/results.py) into table, plain, JSON or CSV text.  They
never talk to a device.

The default follows the terminal (httpie's rule): a rich table when stdout is a
TTY, plain ``ADDRESS VALUE`` lines in a pipe.  rich is imported only when a
table is drawn: it costs tens of milliseconds a cron job should not pay.
"""

from __future__ import annotations

import os
import stat
import sys
from collections.abc import Callable
from typing import TextIO

from mbtool.cli.json_text import to_json
from mbtool.cli.results import (
    PointRow,
    Points,
    Report,
    Result,
    as_dict,
    point_text,
    points_dict,
    report_dict,
    value_text,
)
from mbtool.codec.errors import function_code_text


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
    renderers: dict[str, Callable[..., None]]
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


def value_texts(result: Result) -> list[str]:
    """Each value as plain, table and CSV say it: the command's own words where it gave them
    (write-bit's ``bit 2 on``), else the value's text."""
    return result.texts if result.texts is not None else [value_text(value) for value in result.values]


def by_order(result: Result) -> tuple[str, ...]:
    """The word orders of a --order all result (its values are {order: value}); () otherwise."""
    first = result.values[0] if result.values else None
    return tuple(first) if isinstance(first, dict) else ()


def csv_cells(result: Result) -> tuple[list[str], list[list[str]]]:
    """The CSV header and rows of a result: one column a word order with --order all."""
    orders = by_order(result)
    header = ["ref" if result.refs is not None else "address", *(orders or ["value"])]
    if orders:
        rows = [
            [str(label), *(value_text(value[o]) for o in orders)]
            for label, value in zip(labels(result), result.values, strict=True)
        ]
    else:
        rows = [[str(label), text] for label, text in zip(labels(result), value_texts(result), strict=True)]
    return header, rows


def _plain(result: Result, out: TextIO) -> None:
    out.write(
        "".join(f"{label} {text}\n" for label, text in zip(labels(result), value_texts(result), strict=True))
    )


def _json(result: Result, out: TextIO) -> None:
    out.write(to_json(as_dict(result)) + "\n")


def _csv(result: Result, out: TextIO, wanted: bool) -> None:
    import csv  # noqa: PLC0415 - 0.5 ms: -o csv only

    writer = csv.writer(out, lineterminator="\n")
    header, rows = csv_cells(result)
    if wants_csv_header(out, wanted):
        writer.writerow(header)
    writer.writerows(rows)


def _table(result: Result, out: TextIO) -> None:
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

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
        from mbtool.codec.values import TYPES  # noqa: PLC0415 - typed registers only; crc loads this too

        assert result.type is not None  # not bits
        width = TYPES[result.type].registers
        table.add_column("Registers", justify="right")
    refs = result.refs if result.refs is not None else [None] * len(result.values)
    for index, (ref, address, value) in enumerate(zip(refs, result.addresses, result.values, strict=True)):
        cells = [] if ref is None else [ref]
        if ref is None or not orders:
            cells.append(str(address))
        if result.texts is not None:
            cells.append(result.texts[index])
        elif bits:
            cells.append("[green]ON[/]" if value else "[dim]OFF[/]")
        elif plain_registers:
            # The register as it holds the value: a write of -5 holds 0xFFFB.
            register = value if result.registers is None else result.registers[index]
            cells += [str(value), f"0x{register:04X}"]
        else:
            cells += [value_text(value[o]) for o in orders] if orders else [value_text(value)]
        if typed_registers:
            # The words behind each value: when a float looks wrong, they show the word order.
            start = address - result.address
            assert result.registers is not None  # typed_registers
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


POINT_CSV_HEADER = ["name", "value", "unit", "ref", "registers"]


def point_line(row: PointRow) -> str:
    return f"{row.name} {row.shown} {row.unit if row.value is not None else ''}".rstrip()


def point_cells(row: PointRow) -> list[str]:
    raw = " ".join(value_text(item) for item in row.raw)
    return [row.name, row.shown, row.unit, row.ref, raw]


def points_table(points: Points, heading: str = ""):
    """The rich table of a map read (its heading above it, as polling draws it too)."""
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

    described = any(row.description for row in points.rows)
    table = Table()
    table.add_column("Name", justify="left")
    table.add_column("Value", justify="right")
    table.add_column("Unit", justify="left")
    table.add_column("Ref", justify="right")
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
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only

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
    import csv  # noqa: PLC0415 - 0.5 ms: -o csv only

    writer = csv.writer(out, lineterminator="\n")
    if wants_csv_header(out, wanted):
        writer.writerow(POINT_CSV_HEADER)
    writer.writerows(point_cells(row) for row in points.rows)


# --- structured results: fields, counters, event lists, decoded frames -----------------


def _report_plain(report: Report, out: TextIO) -> None:
    out.write("".join(f"{row.name} {row.shown}\n" for row in report.rows))


def _report_json(report: Report, out: TextIO) -> None:
    out.write(to_json(report_dict(report)) + "\n")


def _report_csv(report: Report, out: TextIO, wanted: bool) -> None:
    import csv  # noqa: PLC0415 - 0.5 ms: -o csv only

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
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

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
