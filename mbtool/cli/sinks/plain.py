"""-o plain: lines a script reads with ``read``/``awk``, the default in a pipe.

A value a line (``ADDRESS VALUE``, a map's ``NAME VALUE UNIT``, a report's ``NAME VALUE``);
a change as ``WHAT: OLD -> NEW``.
"""

from __future__ import annotations

from typing import TextIO

from mbtool.cli.results import (
    Listing,
    PointRow,
    Points,
    Report,
    Result,
    change_parts,
    labels,
    reading_text,
    value_text,
    value_texts,
)


def render(result: Result | Report | Points | Listing, out: TextIO, csv_header: bool = True) -> None:
    if isinstance(result, Listing):
        out.write("".join(line + "\n" for line in result.lines()))
    else:
        out.write(text(result))


def text(result: Result | Report | Points, when: str = "") -> str:
    """The lines of a result, each after ``when`` (a poll's time) when given."""
    stamp = f"{when} " if when else ""
    if isinstance(result, Points):
        lines = (point_line(row) for row in result.rows)
    elif isinstance(result, Report):
        lines = (f"{row.name} {row.shown}" for row in result.rows)
    else:
        lines = (f"{label} {shown}" for label, shown in zip(labels(result), value_texts(result), strict=True))
    return "".join(f"{stamp}{line}\n" for line in lines)


def point_line(row: PointRow) -> str:
    return f"{row.name} {row.shown} {row.unit if row.value is not None else ''}".rstrip()


def change_line(what: dict, old, new, unit: str = "") -> str:
    """``holding 5: 5 -> 99``, ``setpoint (40006): 22.5 m3/h -> 23 m3/h``."""
    where, before, after = change_parts(what, old, new, unit)
    return f"{where}: {before} -> {after}"


class PlantPolls:
    """poll -o plain: a line a point read, ``TIME DEVICE NAME VALUE [UNIT]``."""

    measured = False  # --measurement names its measurement
    exposes = False  # the plant's Prometheus text is not this output

    def __init__(self, out, csv_header: bool, measurement: str, labels: dict | None = None) -> None:
        self.out = out

    def poll(self, poll, when: str) -> None:
        device = poll.device
        for reading in poll.readings or ():
            if reading.error is None:
                unit = f" {reading.point.unit}" if reading.point.unit and reading.value is not None else ""
                self.out.write(f"{when} {device.name} {reading.point.name} {reading_text(reading)}{unit}\n")

    def event(self, event, when: str) -> None:
        """A change of state is on stderr only (plant_text.event_line)."""


class Rows:
    """A stream of rows as they come, and its listing at the end (scan's units as they are
    found): in plain, each row's line at once, flushed, and nothing at the end."""

    def __init__(self, out: TextIO, header: list[str], csv_header: bool = True) -> None:
        self.out = out

    def row(self, cells: list, line: str) -> None:
        self.out.write(line + "\n")
        self.out.flush()

    def end(self, listing: Listing) -> None:
        pass


class Log:
    """A stream of items a line each as they are seen (monitor's frames, bridge's
    transactions): ``views.lines(item)``, the command's plain lines of an item."""

    events = True  # a server's own events (clients connecting) are shown among the items

    def __init__(self, out: TextIO, views, **console_options) -> None:
        self.out = out
        self.views = views

    def write(self, item) -> None:
        self.out.write("".join(line + "\n" for line in self.views.lines(item)))


class Polls:
    """read --interval -o plain: each poll's lines after its time; a change (--changes) as
    ``TIME WHAT: OLD -> NEW``.  The other formats' polls are this one's subclasses, each
    writing what it says otherwise.

    ``output``: the poll's cli.poll_output.Output, whose ``emit`` joins the writes of polls
    close together, and which has the stream, the run's settings and its Readings."""

    changes_as_rows = False  # --changes writes the rows of the values that changed (CSV)
    separator = " "  # between a line's time, label and value

    def __init__(self, output) -> None:
        self.output = output
        # The polls of one read differ only in their time and values: their lines are one
        # %-format of the values, made at the first of them.
        self.read: Result | None = None  # the read (its polls' shared result) ``form`` writes,
        self.form: str | None = None  # and its format (None: the values' text is worked out a poll)

    def result(self, when: str, result, stamp: float | None = None) -> None:
        """A map's points, or a whole result (--changes' first poll and its rows of changes)."""
        if result.__class__ is Points:
            self.output.emit(self.poll_text(when, result))
        else:
            self.read = None  # a result of its own: its format is its own
            self.values(when, result, result.values, result.registers, stamp)

    def values(self, when: str, read: Result, values: list, registers, stamp: float | None = None) -> None:
        """A poll of ``read`` (the result its polls share): its values, and its registers as read."""
        if read is not self.read:
            self.read, self.form = read, self.poll_form(read, values)
        form = self.form
        if form is not None:
            self.output.emit((form % tuple(values)).replace(_TIME, when))
        else:
            self.output.emit(self.poll_text(when, read.polled(values, registers)))

    def poll_form(self, read: Result, values: list) -> str | None:
        """A poll's lines as one %-format of its values, each as value_text writes it: ints and
        bits with %d (a bit as 1 or 0), floats with %r (repr's digits); the time stands as
        _TIME in each line, where one replace puts it.  None for text (CSV quotes it when it
        must; a string read is rarely polled) and --order all's values (a word order each)."""
        kinds = {type(value) for value in values}
        if kinds <= {int, bool}:
            value = "%d"
        elif kinds == {float}:
            value = "%r"
        else:
            return None
        sep = self.separator
        return "".join(
            f"{_TIME}{sep}{self.label(label).replace('%', '%%')}{sep}{value}\n" for label in labels(read)
        )

    @staticmethod
    def label(label: int | str) -> str:
        """An address or a reference as a poll's line names it."""
        return str(label)

    def poll_text(self, when: str, result: Result | Points) -> str:
        """A poll's lines, worked out: a map's points, and values poll_form has no format for."""
        if isinstance(result, Points):
            return text(result, when)
        # A read's values straight to their lines: a poll's are never a command's own words.
        lines = zip(labels(result), result.values, strict=True)
        return "".join(f"{when} {label} {value_text(value)}\n" for label, value in lines)

    def change(self, when: str, what: dict, where: str, old, new, unit: str) -> None:
        """One value that changed since the poll before; ``where`` names it ("": as ``what`` does)."""
        named, before, after = change_parts(what, old, new, unit)
        self.output.emit(f"{when} {where or named}: {before} -> {after}\n")

    def failure(self, when: str, error: BaseException) -> None:
        """A failed poll: its line on stderr is the Output's; stdout has nothing of it."""

    def close(self) -> None:
        pass


_TIME = "\x00"  # stands for a poll's time in its lines' format: no label or number has one
