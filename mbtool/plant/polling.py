"""``read --interval``: the same read again and again over one link, a plant of one device.

Imported only when --interval or --polls is given, so a one-shot read pays nothing for it.  The
polls are the plant's engine's (``plant.schedule.LinkWorker`` on a managed link), run on the
command's own thread: slots on a fixed grid of the monotonic clock (poll k starts at start + k *
interval, so a slow poll or a changed wall clock never makes the schedule drift; a poll that
overruns its slot skips the slots it missed, and says how many), the device never offline, a
link that failed opened again by the one back-off rule (at most once a timeout, so a device
that is restarting or unplugged is not hammered with --interval 0, and the log gets a line a
timeout, not thousands).  A port or unit that makes no sense is a RequestError, one error before
anything is sent.

What a poll shows is not decided here: each reply and failure goes to a ``Shown`` (the CLI's
writes them in the chosen format).  ``poll`` returns a ``Polled`` record: what the polls came to
and the verdict's exit code (0 when every poll got its reply, otherwise the code of the last
failure; 130 only when interrupted before any poll finished).  It writes no words: cli/ turns
the record into the summary line and the --stats json figures.
"""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import Protocol

from mbtool.codec.record import field, record
from mbtool.durations import Durations
from mbtool.errors import ExitCode, NoResponse, PartialRead, exit_code_for
from mbtool.link.connection import Connection, open_client
from mbtool.link.managed import Backoff
from mbtool.link.stats import Stats
from mbtool.plant.schedule import Clock, DeviceSpec, DeviceState, GroupState, LinkSpec, LinkWorker, Poll, Stop

DEFAULT_INTERVAL = 1.0  # seconds, when only --polls is given


class Shown(Protocol):
    """Where the polls go: a reply held to show later, or a failed poll."""

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


class _OneRequest:
    """The reader of a device read with one request: a poll is its reply (the worker makes the
    poll that request's transaction, with no read of this one's)."""

    __slots__ = ("blocks", "request")

    def __init__(self, request) -> None:
        self.blocks = (request,)
        self.request = request

    def read(self, execute):
        return execute(self.request)


class _MapRun:
    """The reader of a poll of several requests: ``run(execute)``, given the link's
    ``execute(unit, request)`` as the plant's readers are given ``execute(request)``."""

    __slots__ = ("run", "unit")
    request = None  # a poll is its reads (plant.schedule.Reader)
    # Its reads are the map's, inside ``run``; only a plant's overrun asks them, and a grid's
    # group never overruns (its late slots are counted as skipped).
    blocks = ()

    def __init__(self, run: Callable, unit: int) -> None:
        self.run, self.unit = run, unit

    def read(self, execute):
        return self.run(lambda unit, request: execute(request))


class _Tally:
    """The polls as the worker reports them: each reply held to show, each failure shown and
    counted (a poll of one request that changed nothing the worker hands to ``Shown.hold``
    itself).  What the worker counts already is asked of it at the end, not counted a poll: the
    polls are the group's, the replies the polls that did not fail, the last poll's time the
    device's last answer's or the last failure's."""

    def __init__(self, shown: Shown, group: GroupState, timed: bool) -> None:
        self.shown = shown
        self.group = group  # the device's one group: its polls are the run's
        self.hold = shown.hold  # bound once: one a poll
        self.partial = self.timeouts = self.errors = 0
        self.last_failure = ExitCode.OK
        self.first_when: float | None = None
        self.failed_when: float | None = None  # the last failed poll's time
        self.per_poll = Durations()
        # How a poll is reported once the first's time is noted (``first``): a map's poll is
        # timed (LinkWorker's timed), one request's by its round trip (the link's stats).
        self.each = self.timed if timed else self.report
        self.worker: LinkWorker  # set once it is made: ``first`` hands it ``each``

    def first(self, item) -> None:
        """What the worker reports until the first poll: that poll's time noted, then each poll
        reported by ``each`` straight, with no check of whether it is the first."""
        if item.__class__ is Poll:
            self.first_when = item.time
            self.worker.report = self.each
        self.each(item)

    def report(self, item) -> None:
        if item.__class__ is not Poll:  # a link's or the device's change of state: its polls say it
            return
        if item.error is None:
            hold = self.hold  # read as an attribute, then called (a method call looks it up generically)
            hold(item.time, item.readings)
        else:
            self._failed(item)

    def timed(self, item) -> None:
        """``report`` of a map's poll, whose latency is counted (None: a reply of it came untimed)."""
        if item.__class__ is Poll and item.latency is not None:
            self.per_poll.add(item.latency)
        self.report(item)

    def _failed(self, item: Poll) -> None:
        error = item.error
        assert error is not None  # a failed poll
        self.failed_when = item.time
        self.shown.write()  # the poll before it, if the request never left
        if isinstance(error, PartialRead):  # some of a map's points: the others are shown
            self.partial += 1
        elif isinstance(error, NoResponse):
            self.timeouts += 1
        else:
            self.errors += 1
        self.last_failure = exit_code_for(error)
        self.shown.failure(item.time, self.group.polls, error)

    def last_when(self, device: DeviceState) -> float | None:
        """The last poll's time: the later of ``device``'s last answer and the last failure."""
        times = [when for when in (device.last_success, self.failed_when) if when is not None]
        return max(times, default=None)


def poll(
    connection: Connection,
    request,
    shown: Shown,
    interval: float | None,
    polls: int | None,
    trace: Callable | None = None,
    run: Callable | None = None,
    clock=None,
) -> Polled:
    """Run ``request`` every ``interval`` seconds, ``polls`` times (0: until interrupted).

    ``trace``: makes each link's Client trace from its framer (--hex).  ``run(execute)``:
    what one poll does when it is more than one request (a register map's reads), given the
    link's ``execute(unit, request)``; ``request`` then stands for them in the link's checks
    (broadcast).  ``clock``: the engine's (None: plant.schedule.Clock, the system's)."""
    clock = clock or Clock
    if interval is None:
        interval = DEFAULT_INTERVAL
    unit = connection.unit
    reader = _OneRequest(request) if run is None else _MapRun(run, unit)
    device = DeviceSpec("", "", unit, reader, {}, interval, offline_after=0, grid=True)
    state = DeviceState(device, clock.monotonic())
    tally = _Tally(shown, state.groups[0], timed=run is not None)
    worker = LinkWorker(
        LinkSpec("", connection),
        [state],
        tally.first,
        Stop(),  # set by no one: Ctrl-C ends this thread's polls
        polls or 0,
        clock=clock,
        open_link=lambda: open_client(connection, request.name, trace=trace),
        # A link that failed is opened again at most once a timeout, as if a refusal had waited
        # the timeout out.
        backoff=Backoff(connection.timeout),
        sent=shown.write,  # the poll before is shown while this one's reply is on its way
        idle=shown.write,
        published=False,
        timed=run is not None,  # a map's poll is timed; one request's, by its round trip
        # A poll of one request that answered and changed nothing is its reply to show, no more.
        answered=shown.hold if run is None else None,
    )
    tally.worker = worker
    interrupted = False
    try:
        # What start-up made (click, the codec's types) lives as long as the run: keep the
        # garbage collector from walking it again every few hundred polls.
        gc.freeze()
        worker.work()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        shown.close()
    polled = tally.group.polls
    code = tally.last_failure
    if interrupted and polled == 0:
        code = ExitCode.INTERRUPTED
    stats = worker.stats
    return Polled(
        polled,
        polled - tally.partial - tally.timeouts - tally.errors,
        tally.partial,
        tally.timeouts,
        tally.errors,
        state.skipped,
        interrupted,
        stats,
        stats.rtt if run is None else tally.per_poll,
        tally.first_when,
        tally.last_when(state),
        tuple(worker.accepted),
        code,
    )
