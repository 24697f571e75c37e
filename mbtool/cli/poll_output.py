"""What polling shows: each poll's reply in the chosen format, stamped, and failed polls.

The polls themselves (schedule, reconnects, the summary's figures) are ``plant.polling``'s; it hands
replies and failures to a ``Deferred`` made here.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from time import monotonic
from typing import TYPE_CHECKING

from mbtool.cli.results import (
    Points,
    PollsOfRead,
    Result,
)
from mbtool.cli.sinks import sink
from mbtool.cli.stamps import local_time
from mbtool.errors import OutputFailed, PartialRead

if TYPE_CHECKING:
    from mbtool.cli.broker import PublishedPolls  # --mqtt's: each poll shown, then published

FLUSH_GAP = 0.05  # seconds: polls closer together than this share a flush


class Output:
    """Writes each poll in the chosen format (its sink's Polls), at once (cron appends to a
    log); polls closer together than FLUSH_GAP (--interval 0) share one write, not a system
    call each, which PYTHONUNBUFFERED or a pipe would otherwise make of every line."""

    def __init__(self, fmt: str, out=None, *, csv_header: bool = True, metrics=None) -> None:
        """``csv_header``: the run's settings (False with --no-header); ``metrics``: the run's
        Readings (cli/metrics.py), for -o influx and prom."""
        self.out = out or sys.stdout
        self.csv_header = csv_header
        self.metrics = metrics
        self._pending: list[str] = []
        self._flush_at = 0.0
        self.pending = _Pending(self)  # a stream for the Readings, that joins these writes
        self.polls = sink(fmt).Polls(self)
        self.result = self.polls.result  # result(when, result, stamp=None): a poll's whole result
        # values(when, read, values, registers, stamp=None): a poll of a read of one request
        self.values = self.polls.values
        self.change = self.polls.change  # change(when, what, where, old, new, unit): --changes

    def failure(self, when: str, number: int, error: BaseException) -> None:
        self.flush()  # the polls before it first, so stdout and stderr stay in order
        print(f"mbtool: {when} poll {number}: {error}", file=sys.stderr, flush=True)
        self.polls.failure(when, error)

    def emit(self, text: str) -> None:
        self._pending.append(text)
        if monotonic() >= self._flush_at:
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
        self._flush_at = monotonic() + FLUSH_GAP

    def close(self) -> None:
        self.flush()
        self.polls.close()


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
        if self.output.polls.changes_as_rows:
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

    def values(self, when: str, read: Result, values: list, registers, stamp: float | None = None) -> None:
        self.result(when, read.polled(values, registers), stamp)

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
    """What the polls show (plant.polling.Shown): a poll's reply is shown while the next
    request is on its way when polls run back to back, so decoding and writing it
    overlaps the device's turnaround instead of adding to every transaction (sustained
    polling keeps pace with a bare client loop).  This one shows a reply as its whole result
    (``to_result``: a map's points); ``DeferredRead`` a read's as its values."""

    def __init__(
        self, output: Output | ChangesOnly | PublishedPolls, to_result: Callable[[object], object]
    ) -> None:
        self.output = output
        self.show = output.result  # show(when, result, stamp): a poll's reply, in the run's format
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
        # to_result and show are attributes, not methods of the class: read as attributes and
        # then called, they are looked up as the interpreter has learnt to, where a method call
        # of them looks them up anew every poll.
        if reply is not self.shown_reply:
            to_result = self.to_result
            self.shown_reply, self.shown_result = reply, to_result(reply)
        show, when = self.show, self.held_when
        show(local_time(when), self.shown_result, when)

    def failure(self, when: float, number: int, error: BaseException) -> None:
        if isinstance(error, PartialRead):  # what was read is shown, then what was not
            self.output.result(local_time(when), self.to_result(error.readings), when)
        self.output.failure(local_time(when), number, error)

    def close(self) -> None:
        self.write()
        self.output.close()


class DeferredRead(Deferred):
    """``Deferred`` of a read of one request (``polls``): a reply is shown as the read and the
    values decoded from it, handed to the output's ``values``, with no Result made a poll."""

    def __init__(self, output: Output | ChangesOnly | PublishedPolls, polls: PollsOfRead) -> None:
        super().__init__(output, polls)
        self.show_values = output.values
        self.read, self.data_of, self.decode, self.raw = polls.read, polls.data_of, polls.decode, polls.raw
        self.shown_values: list = []  # the last reply's values, and its registers (raw)
        self.shown_registers = None

    def write(self) -> None:
        reply = self.held
        if reply is None:
            return
        self.held = None
        if reply is not self.shown_reply:
            data_of, decode = self.data_of, self.decode  # attributes, then called (as Deferred's)
            data = data_of(reply)
            self.shown_reply, self.shown_values = reply, decode(data)
            self.shown_registers = data if self.raw else None
        show, when = self.show_values, self.held_when
        show(local_time(when), self.read, self.shown_values, self.shown_registers, when)


class _Pending:
    """A stream for Readings.emit that joins the Output's pending writes (one flush a gap)."""

    def __init__(self, output: Output) -> None:
        self.output = output

    def write(self, text: str) -> None:
        self.output.emit(text)
