"""-o csv: a header row, then a row a value (a map's point, a report's field).

One header a file: none with --no-header, nor when appending to a regular file that has
content already (cron's ``>> log.csv``); a poll writes it once, its rows after a time column.
"""

from __future__ import annotations

import csv
import os
import stat
from typing import TextIO

from mbtool.cli.results import (
    Listing,
    PointRow,
    Points,
    Report,
    Result,
    by_order,
    labels,
    reading_text,
    value_text,
    value_texts,
)
from mbtool.cli.sinks.plain import Polls as PlainPolls

POINT_CSV_HEADER = ["name", "value", "unit", "ref", "registers"]


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


def writer(out: TextIO):
    return csv.writer(out, lineterminator="\n")


def render(result: Result | Report | Points | Listing, out: TextIO, csv_header: bool = True) -> None:
    if isinstance(result, Listing) and result.table is None:  # no CSV of its own: its lines
        out.write("".join(line + "\n" for line in result.lines()))
        return
    header, rows = rows_of(result)
    rows_writer = writer(out)
    if header and wants_csv_header(out, csv_header):
        rows_writer.writerow(header)
    rows_writer.writerows(rows)


def rows_of(result: Result | Report | Points | Listing) -> tuple[list[str] | None, list[list[str]]]:
    """A result's header (None: a report that has none) and rows, as text."""
    if isinstance(result, Listing):
        assert result.table is not None  # a Listing without one is written as its lines (render)
        return result.table()
    if isinstance(result, Points):
        return POINT_CSV_HEADER, [point_cells(row) for row in result.rows]
    if isinstance(result, Report):
        with_raw = any(row.raw is not None for row in result.rows)
        rows = [
            [
                row.name,
                row.shown,
                *(["" if row.raw is None else row.raw.hex(" ").upper()] if with_raw else []),
            ]
            for row in result.rows
        ]
        return (
            ["name", "value", "bytes"] if with_raw else ["name", "value"]
        ) if result.header else None, rows
    return result_cells(result)


def result_cells(result: Result) -> tuple[list[str], list[list[str]]]:
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


def point_cells(row: PointRow) -> list[str]:
    raw = " ".join(value_text(item) for item in row.raw)
    return [row.name, row.shown, row.unit, row.ref, raw]


def cell(text: str) -> str:
    """A cell as the csv module writes it, without one: values are numbers but for --type
    string, which are quoted the CSV way (a poll's rows are joined by hand, for speed)."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def line(cells: list[str]) -> str:
    return ",".join(map(cell, cells)) + "\n"


class Rows:
    """A stream of rows as they come (scan's units as they are found): each row at once under
    one header, which an empty stream has too (a CSV a reader can load)."""

    def __init__(self, out: TextIO, header: list[str], csv_header: bool = True) -> None:
        self.out = out
        self.header = header
        self.csv_header = csv_header
        self.header_done = False

    def row(self, cells: list, line: str) -> None:
        self._header()
        writer(self.out).writerow(cells)
        self.out.flush()

    def end(self, listing: Listing) -> None:
        self._header()

    def _header(self) -> None:
        if not self.header_done:
            if wants_csv_header(self.out, self.csv_header):
                writer(self.out).writerow(self.header)
            self.header_done = True


PLANT_CSV_HEADER = ["time", "device", "name", "value", "unit", "ref"]


class PlantPolls:
    """poll -o csv: long form, a row a point read, under one header."""

    measured = False  # --measurement names its measurement
    exposes = False

    def __init__(self, out, csv_header: bool, measurement: str, labels: dict | None = None) -> None:
        self.out = out
        self.header = csv_header and wants_csv_header(out)
        self.writer = writer(out)

    def poll(self, poll, when: str) -> None:
        if self.header:
            self.writer.writerow(PLANT_CSV_HEADER)
            self.header = False
        for reading in poll.readings or ():
            if reading.error is None:
                point = reading.point
                self.writer.writerow(
                    [when, poll.device.name, point.name, reading_cell(reading), point.unit, point.ref]
                )

    def event(self, event, when: str) -> None:
        """A change of state is on stderr only (plant_text.event_line)."""


def reading_cell(reading) -> str:
    if reading.value is None:
        return ""  # no data: an empty cell, as a spreadsheet leaves one
    return reading_text(reading) if isinstance(reading.value, bool) else value_text(reading.value)


class Polls(PlainPolls):
    """read --interval -o csv: a row a value after the poll's time, under one header; with
    --changes the rows of the values that changed."""

    changes_as_rows = True
    separator = ","

    def __init__(self, output) -> None:
        super().__init__(output)
        self.header_done = False

    def result(self, when: str, result, stamp: float | None = None) -> None:
        if not self.header_done:
            self._header(POINT_CSV_HEADER if result.__class__ is Points else result_cells(result)[0])
        super().result(when, result, stamp)

    def values(self, when: str, read: Result, values: list, registers, stamp: float | None = None) -> None:
        if not self.header_done:
            self._header(result_cells(read.polled(values, registers))[0])
        super().values(when, read, values, registers, stamp)

    def _header(self, header: list[str]) -> None:
        """The one header of the run's rows (none with --no-header, nor appended to a file that has rows)."""
        if wants_csv_header(self.output.out, self.output.csv_header):
            self.output.emit(",".join(["time", *header]) + "\n")
        self.header_done = True

    @staticmethod
    def label(label: int | str) -> str:
        return cell(str(label))

    def poll_text(self, when: str, result: Result | Points) -> str:
        if isinstance(result, Points):
            rows = [point_cells(row) for row in result.rows]
        else:
            rows = result_cells(result)[1]
        return "".join(",".join([when, *map(cell, row)]) + "\n" for row in rows)
