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

import math
import sys
import time
from collections.abc import Callable

from mbtool.errors import ConnectionFailed, ExitCode, MbtoolError, NoResponse, RequestError, Summary
from mbtool.render import local_time

DEFAULT_INTERVAL = 1.0  # seconds, when only --polls is given


class Output:
    """Writes each poll in the chosen format, flushed at once (cron appends to a log)."""

    def __init__(self, fmt: str, out=None) -> None:
        self.fmt = fmt
        self.out = out or sys.stdout
        self.header_done = False
        self.live = None

    def result(self, when: str, result) -> None:
        from mbtool.render import _text, as_dict

        if self.fmt == "json":
            self.out.write(_json_line({"time": when, **as_dict(result)}))
        elif self.fmt == "csv":
            if not self.header_done:
                self.out.write("time,address,value\n")
                self.header_done = True
            self.out.write("".join(f"{when},{a},{_csv_cell(_text(v))}\n" for a, v in result.items))
        elif self.fmt == "plain":
            self.out.write("".join(f"{when} {a} {_text(v)}\n" for a, v in result.items))
        else:
            self._table(when, result)
        self.out.flush()

    def failure(self, when: str, number: int, error: BaseException) -> None:
        print(f"mbtool: {when} poll {number}: {error}", file=sys.stderr, flush=True)
        if self.fmt == "json":
            # jq consumers read stdout only: a failed poll must show up there too.
            from mbtool.render import to_json

            code = int(getattr(error, "exit_code", ExitCode.INTERNAL))
            self.out.write(to_json({"time": when, "error": str(error), "exit_code": code}) + "\n")
            self.out.flush()

    def _table(self, when: str, result) -> None:
        from rich.console import Group
        from rich.live import Live
        from rich.table import Table
        from rich.text import Text

        from mbtool.render import _text

        # The heading above, not as the table's title: a title wraps to the table's width.
        heading = Text(f"{result.name} (FC {result.function:02d}) · unit {result.unit} · {when}")
        table = Table()
        table.add_column("Address", justify="right")
        table.add_column("Value", justify="right")
        for address, value in result.items:
            table.add_row(str(address), _text(value))
        if self.live is None:
            self.live = Live(Group(heading, table), auto_refresh=False)
            self.live.start()
        self.live.update(Group(heading, table), refresh=True)

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None


def _json_line(data: dict) -> str:
    """The json module's C encoder: a sustained poll spends more on JSON than on Modbus
    with render.to_json, and json's import is nothing to a loop.  The same text, since
    to_json keeps json's separators; NaN and infinities, which json would write as
    invalid JSON, go the to_json way (null)."""
    global _ENCODER
    if _ENCODER is None:
        import json

        _ENCODER = json.JSONEncoder(allow_nan=False)  # made once: json.dumps makes one a call
    try:
        return _ENCODER.encode(data) + "\n"
    except ValueError:
        from mbtool.render import to_json

        return to_json(data) + "\n"


_ENCODER = None


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
    from mbtool.connection import close_quietly, open_client
    from mbtool.render import default_format
    from mbtool.transport import ConnectionClosed

    if interval is None:
        interval = DEFAULT_INTERVAL
    if polls is None:
        polls = 0
    output = Output(connection.output_format or default_format())
    done = replies = timeouts = errors = skipped = 0
    latencies: list[float] = []
    last_failure = ExitCode.OK
    interrupted = False
    link = None  # the open_client context; reopened only after the link itself failed
    client = None
    try:
        # Opened before the first poll: a bad port or unit is one error and its exit code,
        # not a failed poll repeated for ever.
        link = open_client(connection, request.name)
        client = link.__enter__()
        start = time.monotonic()
        slot = 0
        while polls == 0 or done < polls:
            delay = start + slot * interval - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            when = local_time()
            try:
                if client is None:
                    link = open_client(connection, request.name)
                    client = link.__enter__()
                began = time.monotonic()
                reply = client.execute(connection.unit, request)
                latencies.append((time.monotonic() - began) * 1000)
                output.result(when, to_result(reply))
                replies += 1
            except (MbtoolError, OSError) as error:
                if isinstance(error, RequestError):
                    raise  # the request itself is wrong: no later poll can do better
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
                last_failure = error.exit_code
                output.failure(when, done + 1, error)
            done += 1
            slot += 1
            behind = time.monotonic() - (start + slot * interval)
            if interval > 0 and behind > 0 and (polls == 0 or done < polls):
                missed = math.ceil(behind / interval)
                skipped += missed
                slot += missed
    except KeyboardInterrupt:
        interrupted = True
    finally:
        output.close()
        close_quietly(link)
    latency = (
        f"{min(latencies):.1f}/{sum(latencies) / len(latencies):.1f}/{max(latencies):.1f} ms"
        if latencies
        else "-"
    )
    summary = (
        f"polls {done}, replies {replies}, timeouts {timeouts}, errors {errors}, "
        f"skipped {skipped}, latency min/avg/max {latency}"
    )
    if interrupted:
        summary = "interrupted; " + summary
    code = last_failure
    if interrupted and done == 0:
        code = ExitCode.INTERRUPTED
    raise Summary(summary, code)
