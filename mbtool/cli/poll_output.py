"""What polling shows: each poll's reply in the chosen format, stamped, and failed polls.

The loop itself (schedule, reconnects, the summary) is ``link.polling``; it hands
replies and failures to a ``Deferred`` made here.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from mbtool.cli.json_text import JsonLines, error_json, json_line
from mbtool.cli.render import (
    POINT_CSV_HEADER,
    by_order,
    change_parts,
    csv_cells,
    labels,
    point_cells,
    point_line,
    points_heading,
    points_table,
    wants_csv_header,
)
from mbtool.cli.results import Points, Result, points_dict, value_text
from mbtool.cli.settings import MONITORING_FORMATS
from mbtool.cli.stamps import local_time
from mbtool.codec.errors import function_code_text
from mbtool.errors import OutputFailed, PartialRead, exit_code_for

if TYPE_CHECKING:
    from rich.live import Live

FLUSH_GAP = 0.05  # seconds: polls closer together than this share a flush


class Output:
    """Writes each poll in the chosen format, at once (cron appends to a log); polls closer
    together than FLUSH_GAP (--interval 0) share one write, not a system call each, which
    PYTHONUNBUFFERED or a pipe would otherwise make of every line."""

    def __init__(self, fmt: str, out=None, *, csv_header: bool = True, metrics=None) -> None:
        """``csv_header``: the run's settings (False with --no-header); ``metrics``: the run's
        cli.metrics.Metrics, for -o influx and prom."""
        self.fmt = fmt
        self.out = out or sys.stdout
        self.csv_header = csv_header
        self.metrics = metrics
        self.header_done = False
        self.live: Live | None = None  # rich's, made at the first table on a terminal
        self._pending: list[str] = []
        self._flush_at = 0.0
        self._json = JsonLines()

    def result(self, when: str, result, stamp: float | None = None) -> None:
        if self.fmt in MONITORING_FORMATS:
            # To stdout with the other writes (one flush a gap); a textfile is written at once.
            self.metrics.emit(result, None if self.metrics.textfile else _Pending(self), stamp)
        elif result.__class__ is Points:
            self._points(when, result)
        elif self.fmt == "json":
            self._emit(self._json.line(when, result))
        elif self.fmt == "csv":
            header, rows = csv_cells(result)
            self._csv(when, header, rows)
        elif self.fmt == "plain":
            lines = zip(labels(result), result.values, strict=True)
            self._emit("".join(f"{when} {label} {value_text(v)}\n" for label, v in lines))
        else:
            self._table(when, result)

    def change(self, when: str, what: dict, where: str, old, new, unit: str) -> None:
        """One value that changed since the poll before (--changes), as a JSON line or a text
        line; ``where`` names it in the text ("": as ``what`` names it).  CSV writes the rows
        of the values that changed instead (ChangesOnly)."""
        if self.fmt == "json":
            self._emit(
                json_line({"time": when, **what, "old": old, "new": new, **({"unit": unit} if unit else {})})
            )
            return
        named, before, after = change_parts(what, old, new, unit)
        self._emit(f"{when} {where or named}: {before} -> {after}\n")

    def _points(self, when: str, points: Points) -> None:
        if self.fmt == "json":
            self._emit(json_line({"time": when, **points_dict(points)}))
        elif self.fmt == "csv":
            self._csv(when, POINT_CSV_HEADER, [point_cells(row) for row in points.rows])
        elif self.fmt == "plain":
            self._emit("".join(f"{when} {point_line(row)}\n" for row in points.rows))
        else:
            from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: tables only

            self._show_table(Text(f"{points_heading(points)} · {when}"), points_table(points))

    def _csv(self, when: str, header: list[str], rows: list[list[str]]) -> None:
        if not self.header_done:
            if wants_csv_header(self.out, self.csv_header):
                self._emit(",".join(["time", *header]) + "\n")
            self.header_done = True
        self._emit("".join(",".join([when, *map(_csv_cell, row)]) + "\n" for row in rows))

    def failure(self, when: str, number: int, error: BaseException) -> None:
        self.flush()  # the polls before it first, so stdout and stderr stay in order
        print(f"mbtool: {when} poll {number}: {error}", file=sys.stderr, flush=True)
        if self.fmt in MONITORING_FORMATS:  # -o prom and --textfile say the device is down
            self.metrics.emit_failure(error, None if self.metrics.textfile else _Pending(self))
        if self.fmt == "json" and not isinstance(error, PartialRead):
            # jq consumers read stdout only: a failed poll must show up there too (a partial
            # read's line names the points it could not read).
            code = int(exit_code_for(error))
            self._emit(error_json(str(error), code, time=when) + "\n", now=True)

    def _emit(self, text: str, now: bool = False) -> None:
        self._pending.append(text)
        if now or time.monotonic() >= self._flush_at:
            self.flush()

    def flush(self) -> None:
        try:
            if self._pending:
                text = "".join(self._pending)
                self._pending.clear()
                self.out.write(text)
            self.out.flush()
        except BrokenPipeError:
            raise  # the reader went away: cli.main ends quietly
        except OSError as error:  # a full disk: the poll cannot go on
            raise OutputFailed("standard output", error) from None
        self._flush_at = time.monotonic() + FLUSH_GAP

    def _table(self, when: str, result) -> None:
        from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: tables only

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
        self._show_table(heading, table)

    def _show_table(self, heading, table) -> None:
        from rich.console import Group  # noqa: PLC0415 - rich, 12-20 ms: tables only
        from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: tables only

        if not self.out.isatty():
            # Into a file or a pipe every poll's table stays, each ending its line: a table
            # refreshed in place would leave only the last one, without a final newline.
            from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only

            Console(file=self.out).print(Group(heading, table))
            return
        live = self.live
        if live is None:
            live = self.live = Live(Group(heading, table), auto_refresh=False)
            live.start()
        live.update(Group(heading, table), refresh=True)

    def close(self) -> None:
        self.flush()
        if self.live is not None:
            self.live.stop()
            self.live = None


class ChangesOnly:
    """--changes: the first poll whole, then one line a value that changed, so a poll left
    running into a file is a change log (``TIME holding 5: 5 -> 99``; JSON lines with the
    old and new values; CSV rows of the values that changed, under the first poll's header)."""

    def __init__(self, output: Output) -> None:
        self.output = output
        self.previous: dict | None = None

    def result(self, when: str, result, stamp: float | None = None) -> None:
        points = result.__class__ is Points
        # Each value by what names it: a map's point by its name, else its address.
        if points:
            current = {row.name: row.value for row in result.rows}
        else:
            current = dict(zip(result.addresses, result.values, strict=True))
        previous, self.previous = self.previous, current
        if previous is None:
            self.output.result(when, result)
            return
        missing = object()  # a key the poll before did not have: changed from nothing
        changed = {key for key, value in current.items() if not _same(previous.get(key, missing), value)}
        if not changed:
            return
        if self.output.fmt == "csv":
            # One header for the whole log: the rows of the values that changed, as the
            # first poll wrote its rows.
            self.output.result(when, _only(result, changed))
            return
        if points:
            for row in result.rows:
                if row.name in changed:
                    what = {"name": row.name, "ref": row.ref}
                    self.output.change(when, what, "", previous.get(row.name), row.value, row.unit)
            return
        refs, table = result.refs, result.table
        for index, (address, value) in enumerate(zip(result.addresses, result.values, strict=True)):
            if address in changed:
                what = {"unit": result.unit, "table": table, "address": address}
                if refs is not None:  # named by the reference the user gave, as its first poll was
                    what["ref"] = refs[index]
                where = "" if refs is None else refs[index]
                self.output.change(when, what, where, previous.get(address), value, "")

    def failure(self, when: str, number: int, error: BaseException) -> None:
        self.output.failure(when, number, error)

    def close(self) -> None:
        self.output.close()


def _same(old, new) -> bool:
    """Equal, or NaN both times: NaN equals nothing, itself included, and a register that
    keeps reading NaN has not changed (--order all: each order's value alike)."""
    if isinstance(old, dict) and isinstance(new, dict):
        return old.keys() == new.keys() and all(_same(old[order], new[order]) for order in old)
    return old == new or old != old and new != new


def _only(result, keys: set):
    """A poll's result cut to the values ``keys`` name (points by name, values by address)."""
    if result.__class__ is Points:
        return Points(result.unit, result.source, [row for row in result.rows if row.name in keys])
    kept = [i for i, address in enumerate(result.addresses) if address in keys]
    return Result(
        result.unit,
        result.function,
        result.name,
        result.address,
        [result.values[i] for i in kept],
        result.type,
        None,
        "",
        result.extra,
        None if result.refs is None else [result.refs[i] for i in kept],
        [result.addresses[i] for i in kept],
    )


class Deferred:
    """What the poll loop shows (link.polling.Shown): a poll's reply is shown while the next
    request is on its way when polls run back to back, so decoding and writing it
    overlaps the device's turnaround instead of adding to every transaction (sustained
    polling keeps pace with a bare client loop)."""

    def __init__(self, output: Output | ChangesOnly, to_result: Callable[[object], object]) -> None:
        self.output = output
        self.to_result = to_result
        self.held = None  # the reply to show, and when its request left (time.time())
        self.held_when = 0.0
        # The last reply shown and its result: the client hands back the same response for
        # the same reply bytes, and a poll whose values have not changed is not worked out
        # again.
        self.shown_reply = self.shown_result = None

    def hold(self, when: float, reply) -> None:
        """Keep a reply to show later; the one before it went out with the request."""
        self.held, self.held_when = reply, when

    def write(self) -> None:
        reply = self.held
        if reply is None:
            return
        self.held = None
        if reply is not self.shown_reply:
            self.shown_reply, self.shown_result = reply, self.to_result(reply)
        when = self.held_when
        self.output.result(local_time(when), self.shown_result, when)

    def failure(self, when: float, number: int, error: BaseException) -> None:
        if isinstance(error, PartialRead):  # what was read is shown, then what was not
            self.output.result(local_time(when), self.to_result(error.readings), when)
        self.output.failure(local_time(when), number, error)

    def close(self) -> None:
        self.write()
        self.output.close()


class _Pending:
    """A stream for Metrics.emit that joins the Output's pending writes (one flush a gap)."""

    def __init__(self, output: Output) -> None:
        self.output = output

    def write(self, text: str) -> None:
        self.output._emit(text)


def _csv_cell(text: str) -> str:
    # Values are numbers except for --type string; quote those the CSV way.
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text
