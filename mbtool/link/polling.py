"""Polling: the same read again and again over one link, each poll stamped, failures counted.

Imported only when --interval or --polls is given, so a one-shot read pays nothing
for it.  Polls are scheduled on the monotonic clock (poll k starts at
start + k * interval), so a slow poll or a changed wall clock never makes the
schedule drift; a poll that overruns its slot skips the slots it missed, and
says how many in the summary.

What a poll shows is not decided here: the loop hands each reply and failure to a
``Shown`` (the CLI's writes them in the chosen format).

The loop returns a ``Polled`` record: what the polls came to and the verdict's exit code (0
when every poll got its reply, otherwise the code of the last failure; 130 only when
interrupted before any poll finished).  It writes no words: cli/ turns the record into the
summary line and the --stats json figures.
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from typing import Protocol

from mbtool.codec.errors import RequestError
from mbtool.codec.record import field, record
from mbtool.durations import Durations
from mbtool.errors import (
    KNOWN_ERRORS,
    ExitCode,
    NoResponse,
    OutputFailed,
    PartialRead,
    UsageError,
    exit_code_for,
    link_failure,
)
from mbtool.link.connection import open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats

DEFAULT_INTERVAL = 1.0  # seconds, when only --polls is given


class Shown(Protocol):
    """Where the loop puts what it gets: a reply held to show later, or a failed poll."""

    def hold(self, when: float, reply) -> None: ...  # when: time.time() the poll's request left

    def write(self) -> None: ...  # show the reply held, if any

    def failure(self, when: float, number: int, error: BaseException) -> None: ...

    def close(self) -> None: ...


@record
class Polled:
    """What a run of polls came to: the counts, the transactions' outcomes (``stats``), each
    poll's latency (``per_poll``: a map read's, from its first request to its last reply; a
    single request's is its round trip), when the first and last poll were made (time.time()),
    the deviations --lenient let through, and the verdict's exit code."""

    polls: int
    replies: int
    partial: int
    timeouts: int
    errors: int
    skipped: int
    interrupted: bool
    stats: Stats = field(compare=False)
    per_poll: Durations = field(compare=False)
    first_when: float | None
    last_when: float | None
    accepted: tuple[str, ...]
    exit_code: ExitCode


def poll(
    connection,
    request,
    shown: Shown,
    interval: float | None,
    polls: int | None,
    trace: Callable | None = None,
    run: Callable | None = None,
) -> Polled:
    """Run ``request`` every ``interval`` seconds, ``polls`` times (0: until interrupted).

    ``trace``: makes each link's Client trace from its framer (--hex).  ``run(execute)``:
    what one poll does when it is more than one request (a register map's reads), given the
    link's ``execute(unit, request)``; ``request`` then stands for them in the link's checks
    (broadcast)."""

    if interval is None:
        interval = DEFAULT_INTERVAL
    scheduled = interval > 0  # back to back (0) keeps no schedule; asked once, not twice a poll
    limit = polls or math.inf  # 0 or None: until interrupted
    # A poll that ends is a reply or one failure counted: the replies are the polls less those.
    done = partial = timeouts = errors = skipped = 0
    # A request's latency runs from it leaving to its reply (the client's rtt, which
    # link.stats counts with every transaction's outcome); a poll's from its first request
    # leaving to its last reply (a map read is several requests, each perhaps --pause apart).
    # A reply that came while mbtool was busy (the poll before written to a slow pipe) has no
    # known arrival: it is counted untimed, and the poll it is part of left out too.
    stats, per_poll = Stats(), Durations()
    accepted: dict[str, None] = {}  # deviations --lenient let through, each kind once
    last_failure = ExitCode.OK
    interrupted = False
    pause, unit, reconnect_each = connection.pause, connection.unit, connection.reconnect_each
    # The link is opened by the first poll, as by a poll after a lost link: a device that is not
    # up yet is a failed poll, and polling goes on.  A link that failed is opened again at most
    # once a timeout, as if a refusal had waited the timeout out, so a device that is restarting
    # or unplugged is not hammered (with --interval 0) and the log gets a line a timeout, not
    # thousands.  A port or unit that makes no sense is a UsageError, one error before
    # anything is sent.
    link = ManagedLink(
        lambda: open_client(connection, request.name, trace=trace), Backoff(connection.timeout), stats, time
    )
    client = None
    when = first_when = last_when = None  # time.time() of this poll, the first and the last

    def request_sent() -> None:
        """Run by the client right after a poll's (first) request has left: that is the poll's
        time, and the poll before it is shown while the reply is on its way."""
        nonlocal when
        when = time.time()
        show_previous()

    try:
        # What start-up made (click, the codec's types) lives as long as the loop: keep the
        # garbage collector from walking it again every few hundred polls.
        gc.freeze()
        start = time.monotonic()
        slot = 0
        show_previous = shown.write  # bound once, not a method object a poll
        execute = link.execute
        while done < limit:
            if scheduled:
                delay = start + slot * interval - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            client = link.client
            when = None  # until the request goes out
            try:
                if client is None:
                    link.wait()  # a link that failed waits out its back-off
                    client = link.open()
                    if done == 0:
                        # The first link's modules stay as long as the loop too; and the schedule
                        # starts with the first link open: opening sim:// (its imports) or a
                        # slow handshake is not a poll overrunning its slot.
                        gc.freeze()
                        start = time.monotonic()
                client.while_waiting = request_sent
                if run is None:  # one request: the poll's latency is the request's round trip
                    reply = execute(unit, request)
                else:
                    untimed = stats.untimed
                    reply = run(execute)
                    if stats.untimed == untimed:  # every reply of the poll timed
                        per_poll.add(client.replied_at - client.work_sent_at)
                if client.deviations:  # --lenient took a reply as it was: the summary says so
                    accepted.update(client.deviations)
            except BrokenPipeError:
                raise  # stdout's reader went away: nothing left to poll for
            except (*KNOWN_ERRORS, OSError) as error:
                shown.write()  # the poll before it, if the request never left
                if isinstance(error, RequestError | UsageError | OutputFailed):
                    raise  # the request is wrong, or the output full: no later poll can do better
                if when is None:  # the request never left: the poll failed now
                    when = time.time()
                if isinstance(error, PartialRead):  # some of a map's points: the others are shown
                    partial += 1
                elif isinstance(error, NoResponse):
                    timeouts += 1
                else:
                    errors += 1
                error = link_failure(error)
                if client is None:  # the link could not be opened: the request never went
                    stats.transaction(error, 0)
                # A lost link (device restarted, cable pulled) was closed by the managed link,
                # which opens it anew next poll.
                last_failure = exit_code_for(error)
                shown.failure(when, done + 1, error)
            else:
                assert when is not None  # set by request_sent: the reply answers a request that left
                shown.hold(when, reply)
            if done == 0:
                first_when = when
            last_when = when
            if reconnect_each and link.client is not None:
                # --reconnect-each: a new link every poll, for devices and gateways that
                # serve one client or leak connections; no wait, as nothing failed.
                link.drop(on_purpose=True)
            done += 1
            # Show the poll now unless the next request leaves at once (then it is shown while
            # that request's reply is on its way): a pause, a new link or a slot not yet due
            # come first.
            if scheduled:
                slot += 1
                behind = time.monotonic() - (start + slot * interval)
                if behind < 0:
                    shown.write()
                    continue
                if behind > 0 and done < limit:
                    missed = math.ceil(behind / interval)
                    skipped += missed
                    slot += missed
            if pause or link.client is None:
                shown.write()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        shown.close()
        link.close()
    code = last_failure
    if interrupted and done == 0:
        code = ExitCode.INTERRUPTED
    return Polled(
        done,
        done - partial - timeouts - errors,
        partial,
        timeouts,
        errors,
        skipped,
        interrupted,
        stats,
        stats.rtt if run is None else per_poll,
        first_when,
        last_when,
        tuple(accepted),
        code,
    )
