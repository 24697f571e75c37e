"""-o table: rich's tables, the default on a terminal; and every other thing mbtool draws
with rich (live views, progress bars).  This is the one module that imports rich: it is
imported inside each function, as it costs a one-shot that writes no table 12-20 ms.
"""

from __future__ import annotations

import sys
from typing import TextIO

from mbtool.cli.results import Points, Report, Result, by_order, labels, points_heading, value_text
from mbtool.cli.sinks.plain import Polls as PlainPolls
from mbtool.codec.errors import function_code_text


def render(result: Result | Report | Points, out: TextIO, csv_header: bool = True) -> None:
    if isinstance(result, Points):
        _points(result, out)
    elif isinstance(result, Report):
        _report(result, out)
    else:
        _result(result, out)


def console(out: TextIO | None = None):
    """rich's console on ``out`` (stdout when None or stdout: rich then finds the terminal's width)."""
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only

    return Console(file=out) if out is not None and out is not sys.stdout else Console()


def _result(result: Result, out: TextIO) -> None:
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
            words = result.registers[start : start + (width or len(result.registers))]
            cells.append(" ".join(f"{w:04X}" for w in words))
        table.add_row(*cells)
    shown = console(out)
    shown.print(
        f"[bold]{result.name}[/] · {function_code_text(result.function)} · unit {result.unit}",
        highlight=False,
    )
    shown.print(table)
    if result.note:
        shown.print(result.note, style="dim")


def points_table(points: Points, heading: str = ""):
    """The rich table of a map read (its heading above it, as polling draws it too)."""
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

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


def _points(points: Points, out: TextIO) -> None:
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only

    shown = console(out)
    shown.print(f"[bold]{escape(points_heading(points))}[/]", highlight=False)
    shown.print(points_table(points))
    if points.note:
        shown.print(escape(points.note), style="dim")


def _report(report: Report, out: TextIO) -> None:
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
    shown = console(out)
    title = report.title
    if not title:
        title = f"[bold]{escape(report.name)}[/]"
        if report.function is not None:
            title += f" · {function_code_text(report.function)}"
        if report.unit is not None:
            title += f" · unit {report.unit}"
    shown.print(title, highlight=False)
    shown.print(table)
    if report.note:
        shown.print(escape(report.note), style="dim")


class Polls(PlainPolls):
    """read --interval -o table: each poll's table under its heading, redrawn in place on a
    terminal; into a file or a pipe every poll's table stays."""

    def __init__(self, output) -> None:
        super().__init__(output)
        self.live = None

    def result(self, when: str, result, stamp: float | None = None) -> None:
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: tables only

        if result.__class__ is Points:
            self._show(Text(f"{points_heading(result)} · {when}"), points_table(result))
            return
        from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

        # The heading above, not as the table's title: a title wraps to the table's width.
        heading = Text(f"{result.name} · {function_code_text(result.function)} · unit {result.unit} · {when}")
        orders = by_order(result)
        table = Table()
        table.add_column("Ref" if result.refs is not None else "Address", justify="right")
        for column in orders or ["Value"]:
            table.add_column(column, justify="right")
        for label, value in zip(labels(result), result.values, strict=True):
            values = [value_text(value[o]) for o in orders] if orders else [value_text(value)]
            table.add_row(str(label), *values)
        self._show(heading, table)

    def _show(self, heading, table) -> None:
        from rich.console import Group  # noqa: PLC0415 - rich, 12-20 ms: tables only
        from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: tables only

        out = self.output.out
        if not out.isatty():
            # Into a file or a pipe every poll's table stays, each ending its line: a table
            # refreshed in place would leave only the last one, without a final newline.
            console(out).print(Group(heading, table))
            return
        if self.live is None:
            self.live = Live(Group(heading, table), auto_refresh=False)
            self.live.start()
        self.live.update(Group(heading, table), refresh=True)

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None
