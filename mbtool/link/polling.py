"""Polling: the same read again and again over one link, each poll stamped, failures counted.

Imported only when --interval or --polls is given, so a one-shot read pays nothing
for it.  Polls are scheduled on the monotonic clock (poll k starts at
start + k * interval), so a slow poll or a changed wall clock never makes the
schedule drift; a poll that overruns its slot skips the slots it missed, and
says how many in the summary.

The summary leaves as one ``mbtool:`` line through cli.main, like every error,
carrying the exit code: 0 when every poll got its reply, otherwise the code of
the last failure; 130 only when interrupted before any poll finished.
"""

from __future__ import annotations

import gc
import math
import sys
import time
from collections.abc import Callable

from mbtool.cli.render import local_time
from mbtool.codec.errors import RequestError
from mbtool.errors import (
    KNOWN_ERRORS,
    ConnectionFailed,
    ExitCode,
    NoResponse,
    OutputFailed,
    Summary,
    exit_code_for,
)

DEFAULT_INTERVAL = 1.0  # seconds, when only --polls is given


FLUSH_GAP = 0.05  # seconds: polls closer together than this share a flush


class Output:
    """Writes each poll in the chosen format, at once (cron appends to a log); polls closer
    together than FLUSH_GAP (--interval 0) share one write, not a system call each, which
    PYTHONUNBUFFERED or a pipe would otherwise make of every line."""

    def __init__(self, fmt: str, out=None) -> None:
        self.fmt = fmt
        self.out = out or sys.stdout
        self.header_done = False
        self.live = None
        self._pending: list[str] = []
        self._flush_at = 0.0

    def result(self, when: str, result) -> None:
        from mbtool.cli.render import _text, as_dict

        if self.fmt == "json":
            self._emit(_json_line({"time": when, **as_dict(result)}))
        elif self.fmt == "csv":
            if not self.header_done:
                from mbtool.cli.render import wants_csv_header

                if wants_csv_header(self.out):
                    self._emit("time,address,value\n")
                self.header_done = True
            self._emit("".join(f"{when},{a},{_csv_cell(_text(v))}\n" for a, v in result.items))
        elif self.fmt == "plain":
            self._emit("".join(f"{when} {a} {_text(v)}\n" for a, v in result.items))
        else:
            self._table(when, result)

    def failure(self, when: str, number: int, error: BaseException) -> None:
        self.flush()  # the polls before it first, so stdout and stderr stay in order
        print(f"mbtool: {when} poll {number}: {error}", file=sys.stderr, flush=True)
        if self.fmt == "json":
            # jq consumers read stdout only: a failed poll must show up there too.
            from mbtool.cli.render import error_json

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
        from rich.console import Group
        from rich.live import Live
        from rich.table import Table
        from rich.text import Text

        from mbtool.cli.render import _text

        # The heading above, not as the table's title: a title wraps to the table's width.
        heading = Text(f"{result.name} (FC {result.function:02d}) · unit {result.unit} · {when}")
        table = Table()
        table.add_column("Address", justify="right")
        table.add_column("Value", justify="right")
        for address, value in result.items:
            table.add_row(str(address), _text(value))
        if not self.out.isatty():
            # Into a file or a pipe every poll's table stays, each ending its line: a table
            # refreshed in place would leave only the last one, without a final newline.
            from rich.console import Console

            Console(file=self.out).print(Group(heading, table))
            return
        if self.live is None:
            self.live = Live(Group(heading, table), auto_refresh=False)
            self.live.start()
        self.live.update(Group(heading, table), refresh=True)

    def close(self) -> None:
        self.flush()
        if self.live is not None:
            self.live.stop()
            self.live = None


class Deferred:
    """A poll's reply, shown while the next request is on its way when polls run back to
    back: decoding and writing it then overlaps the device's turnaround instead of
    adding to every transaction (sustained polling keeps pace with a bare client loop)."""

    def __init__(self, output: Output, to_result: Callable[[object], object]) -> None:
        self.output = output
        self.to_result = to_result
        self.held: tuple[float, object] | None = None

    def hold(self, when: float, reply) -> None:
        """Keep a reply to show later; the one before it went out with the request."""
        self.held = (when, reply)

    def write(self) -> None:
        if self.held is not None:
            when, reply = self.held
            self.held = None
            self.output.result(local_time(when), self.to_result(reply))


class Latency:
    """Min, average and max in constant memory: a poll left running for weeks keeps no list."""

    def __init__(self) -> None:
        self.count, self.total, self.low, self.high = 0, 0.0, math.inf, 0.0

    def add(self, ms: float) -> None:
        self.count += 1
        self.total += ms
        # Comparisons, not min() and max(): this runs between a reply and the next request.
        if ms < self.low:
            self.low = ms
        if ms > self.high:
            self.high = ms

    def __str__(self) -> str:
        if not self.count:
            return "-"
        return f"{self.low:.1f}/{self.total / self.count:.1f}/{self.high:.1f} ms"


def _json_line(data: dict) -> str:
    """The json module's C encoder: a sustained poll spends more on JSON than on Modbus
    with render.to_json, and json's import is nothing to a loop.  The same text, since
    to_json keeps json's separators; NaN and infinities, which json would write as
    invalid JSON, go the to_json way (null)."""
    global _ENCODER
    if _ENCODER is None:
        import json

        # Made once (json.dumps makes one a call); a poll's data has no cycles to look for.
        _ENCODER = json.JSONEncoder(allow_nan=False, check_circular=False)
    try:
        return _ENCODER.encode(data) + "\n"
    except ValueError:
        from mbtool.cli.render import to_json

        return to_json(data) + "\n"


_ENCODER = None


def _rate(per_second: float) -> str:
    """Polls a second, from first poll to last: whole numbers when fast, two figures when slow (cron)."""
    return f"{per_second:.0f}" if per_second >= 10 else f"{per_second:.2g}"


def _csv_cell(text: str) -> str:
    # Values are numbers except for --type string; quote those the CSV way.
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def poll(
    connection,
    request,
    to_result: Callable[[object], object],
    interval: float | None,
    polls: int | None,
) -> None:
    """Run ``request`` every ``interval`` seconds, ``polls`` times (0: until interrupted)."""
    from mbtool.cli.render import default_format
    from mbtool.link.connection import close_quietly, open_client
    from mbtool.link.transport import ConnectionClosed

    if interval is None:
        interval = DEFAULT_INTERVAL
    if polls is None:
        polls = 0
    output = Output(connection.output_format or default_format())
    shown = Deferred(output, to_result)
    done = replies = timeouts = errors = skipped = 0
    latency = Latency()
    last_failure = ExitCode.OK
    interrupted = False
    link = None  # the open_client context; reopened only after the link itself failed
    client = None
    try:
        # Opened before the first poll: a bad port or unit is one error and its exit code,
        # not a failed poll repeated for ever.
        opened_at = time.monotonic()
        link = open_client(connection, request.name)
        client = link.__enter__()
        # What start-up made (click, the codec's types) lives as long as the loop: keep the
        # garbage collector from walking it again every few hundred polls.
        gc.freeze()
        start = time.monotonic()
        slot = 0
        show_previous = shown.write  # bound once, not a method object a poll
        while polls == 0 or done < polls:
            if interval > 0:  # back to back (0) keeps no schedule
                delay = start + slot * interval - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if client is None:
                # The link failed: open it again at most once a timeout, as if a refusal had
                # waited the timeout out, so a device that is restarting or unplugged is not
                # hammered (with --interval 0) and the log gets a line a timeout, not thousands.
                wait = opened_at + connection.timeout - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            when = time.time()  # formatted when shown, off the request's path
            if done == 0:
                first_when = when
            try:
                if client is None:
                    opened_at = time.monotonic()
                    link = open_client(connection, request.name)
                    client = link.__enter__()
                client.while_waiting = show_previous
                reply = client.execute(connection.unit, request)
                latency.add(client.round_trip * 1000)
                replies += 1
            except BrokenPipeError:
                raise  # stdout's reader went away: nothing left to poll for
            except (*KNOWN_ERRORS, OSError) as error:
                shown.write()  # the poll before it, if the request never left
                if isinstance(error, RequestError | OutputFailed):
                    raise  # the request is wrong, or the output full: no later poll can do better
                if isinstance(error, NoResponse):
                    timeouts += 1
                else:
                    errors += 1
                if isinstance(error, OSError | ConnectionFailed | ConnectionClosed):
                    # The link is gone (device restarted, cable pulled): open it anew next poll.
                    close_quietly(link)
                    link = client = None
                if isinstance(error, OSError):
                    error = ConnectionFailed(str(error))
                last_failure = exit_code_for(error)
                output.failure(local_time(when), done + 1, error)
            else:
                shown.hold(when, reply)
            done += 1
            if interval > 0:
                slot += 1
                behind = time.monotonic() - (start + slot * interval)
                if behind < 0:
                    shown.write()  # the next poll is not due yet: no reason to hold this one
                elif behind > 0 and (polls == 0 or done < polls):
                    missed = math.ceil(behind / interval)
                    skipped += missed
                    slot += missed
    except KeyboardInterrupt:
        interrupted = True
    finally:
        shown.write()
        output.close()
        close_quietly(link)
    summary = (
        f"polls {done}, replies {replies}, timeouts {timeouts}, errors {errors}, "
        f"skipped {skipped}, latency min/avg/max {latency}"
    )
    if done > 1 and when > first_when:
        summary += f", {_rate((done - 1) / (when - first_when))} polls/s"
    if interrupted:
        summary = "interrupted; " + summary
    code = last_failure
    if interrupted and done == 0:
        code = ExitCode.INTERRUPTED
    raise Summary(summary, code)
