"""The plant: every device of several links, one transaction at a time on each link,
every link at once.

A link (a serial bus, or a gateway or TCP device that takes one request at a time) has a
worker thread of its own, every one started before any opens its link: a plant of more
links than the system allows threads is refused whole (exit 6), not cut short mid-run.  It opens the link, and polls its devices as they fall due: when
several are due, the one that has waited longest goes first.  A poll reads every point of
the device (``MapReader``); the client keeps the line's silences and ``pause``.

A device that fails ``offline_after`` polls in a row (no response, a bad frame, an exception
to every read) is offline: it is tried again after a back-off that doubles from twice its
interval up to ``max_backoff``, so a dead meter costs one timeout a back-off, not one a poll
of the others.  One good poll brings it back online.  A link that cannot be opened (a
missing port, a refused connection) backs off the same way, and its devices are offline
meanwhile.  Each change of state is an ``Event``; each poll a ``Poll``: immutable records that
the link's thread publishes to one queue, drained by the thread that runs the plant, which
alone hands them to ``report`` (the output, the live view, the exporter's text).  So data flows
one way: a link thread is the only one that changes its devices' state, and what the rest of
mbtool shows comes from the records.

``read --interval`` is a plant of one device (``plant.polling``): its worker runs on the
command's own thread, its slots on a fixed grid (``DeviceSpec.grid``: one that has passed is
skipped and counted), the device never offline (``offline_after`` 0: a run of --polls ends on
its polls, not on a link that would not open), its records unpublished copies of nothing (no
reader on another thread: ``published``), and hooks for the output (``sent``: the poll's
request has left, so the poll before is shown while the reply is on its way; ``idle``: the
worker is about to wait).  A request the link cannot carry (``RequestError``, ``UsageError``),
an output that failed and a reader of stdout gone end the run: no later poll can do better.

A run that ends (``rounds``, a duration) makes no promise it cannot keep: a back-off that
would end after the run is announced without its next try.  With ``rounds`` a device is done
once polled that many times, and an offline one is tried again only where its back-off ends
before the last poll the link's other devices still have to make: so every device that
answers gets its rounds, an offline one fewer, and the run does not wait out a back-off.
"""

from __future__ import annotations

import _thread
import functools
import gc
import math
import queue
import threading
import time
from collections.abc import Callable, Collection, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

from mbtool.codec.errors import RequestError
from mbtool.codec.record import field, fields_setter, record, replace
from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, OutputFailed, PartialRead, UsageError, link_failure
from mbtool.link.connection import Connection, open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats
from mbtool.plant.budget import serial_line, transaction_seconds
from mbtool.plant.stats import DeviceAndLink, PollStats
from mbtool.registermap.groups import DEFAULT
from mbtool.registermap.plan import Reading

if TYPE_CHECKING:
    from mbtool.link.client import Client

ONLINE, OFFLINE, UNKNOWN = "online", "offline", "unknown"
# Seconds for every link's worker thread to start: one starts in a millisecond or so.
START_WITHIN = 5.0
OVERRUN = "overrun"  # a link's event: its groups ask more reads a second than it carries
LATE = 0.1  # of its interval: a group's poll that starts later than that after its slot overran
# What ends a run rather than fails a poll: a request the link cannot carry (no later poll can
# do better), the output that failed, and stdout's reader gone.
FATAL = (RequestError, UsageError, OutputFailed, BrokenPipeError)


class Reader(Protocol):
    """What a group's poll reads, given ``execute(request)`` on its link: a register map's
    points (``MapReader``), or read --interval's request or requests."""

    # The one request a poll of it is, when that is all it reads (read --interval's): the poll
    # is that request's transaction, with no read of the reader's; None: a poll is ``read``.
    request: Any

    @property
    def blocks(self) -> Sequence[Any]:
        """Its reads a poll: what its pace asks of the line."""
        ...

    def read(self, execute: Callable) -> Any: ...


@record
class Group:
    """Some of a device's points, read at their own pace (registermap/groups.py): the group's
    name, its interval (math.inf: once, at start and after each reconnect) and its reads."""

    name: str
    interval: float
    reader: Reader = field(compare=False)


@record
class DeviceSpec:
    """A device of the inventory: where it is, what to read, how often."""

    name: str
    link: str
    unit: int
    reader: Reader = field(compare=False)
    tags: dict = field(default=None, compare=False)
    interval: float = 10.0
    offline_after: int = 3
    max_backoff: float = 300.0
    raw: bool = False  # it reads references (raw registers and bits), not a map's points
    measurement: str | None = None  # its InfluxDB measurement; None: the run's (poll --measurement)
    timeout: float | None = None  # its own, where it is slower than its link's other devices
    retries: int | None = None  # None: the link's
    # Its poll groups, the default one (its points in no group) among them; none: one group,
    # every point at ``interval``.  ``reader`` reads every point of it all the same.
    groups: tuple[Group, ...] = field(default=(), compare=False)
    # Its slots on a fixed grid from its first poll (read --interval): one that has passed is
    # skipped and counted, and the next slot of the grid waited for; else (a plant) a group
    # late for its slot is polled at once, and its interval runs from there.
    grid: bool = False

    def paced(self) -> tuple[Group, ...]:
        """The groups its points are polled in."""
        return self.groups or (Group(DEFAULT, self.interval, self.reader),)

    @property
    def fastest(self) -> float:
        """Its shortest interval (of its groups read more than once): its back-off starts at twice it."""
        return min(
            (group.interval for group in self.groups if group.interval < math.inf), default=self.interval
        )


@record
class LinkSpec:
    """A link of the inventory: a Connection whose unit each device gives."""

    name: str
    connection: Connection


def limits(device: DeviceSpec, link: LinkSpec) -> tuple[float, int]:
    """The timeout and retries a device's transactions have: its own, else its link's."""
    connection = link.connection
    return (
        connection.timeout if device.timeout is None else device.timeout,
        connection.retries if device.retries is None else device.retries,
    )


class Poll(NamedTuple):
    """One device poll: its readings (all, or some with PartialRead as ``error``), or the
    error that kept it from reading any.  Made in every poll, it is a tuple: immutable, and
    made in C (``_poll_of``)."""

    device: DeviceSpec
    time: float  # time.time(): when its first request went out, or when it failed
    readings: list[Reading] | None
    error: BaseException | None
    state: str  # the device's state after the poll
    # The device and its link as the poll left them, copies no later poll changes: what a
    # reader shows of them comes from here, never from the link thread's own state.
    last_success: float | None = None  # time.time()
    stats: PollStats | None = None
    link: LinkView | None = None
    group: str = DEFAULT  # the group it read: its readings are that group's points
    # How that group keeps its interval: a device of groups' (None: one of no groups, whose
    # pace is its interval's, in its summary).
    pace: Pace | None = None
    # A device of several groups: the latest reading of every point it has read, this poll's
    # and the other groups' (the Prometheus text and the live view show each point's last value).
    latest: tuple[Reading, ...] | None = None
    # From its first request leaving to its last reply; None: a reply of it came untimed (while
    # mbtool was busy), it failed, or its worker does not time polls (LinkWorker's ``timed``).
    latency: float | None = None


# A Poll of the values of its twelve fields, in their order: Poll._make without its check of
# their count, and with no frame of Python.
_poll_of = functools.partial(tuple.__new__, Poll)


@record
class Pace:
    """How a group keeps its interval: the interval asked, the mean achieved between its polls
    (None before two), its polls and its overruns (polls that started later than ``LATE`` of
    its interval after their slot, and slots skipped while a poll took longer than it)."""

    group: str
    asked: float
    achieved: float | None
    polls: int
    overruns: int

    def __init__(self, group, asked, achieved, polls, overruns) -> None:
        # By hand, its fields one table: one a poll (codec/record.py says why).
        _pace_fields(
            self, {"group": group, "asked": asked, "achieved": achieved, "polls": polls, "overruns": overruns}
        )


_pace_fields = fields_setter(Pace)


@record
class LinkView:
    """A link as its thread saw it when it published a record: its state, the opens that failed
    and its devices' transactions."""

    name: str
    state: str
    open_failures: int
    stats: Stats = field(compare=False)

    def __init__(self, name, state, open_failures, stats) -> None:
        # By hand, its fields one table: one a poll (codec/record.py says why).
        _link_view_fields(
            self, {"name": name, "state": state, "open_failures": open_failures, "stats": stats}
        )


_link_view_fields = fields_setter(LinkView)


@record
class DeviceView:
    """A device as a reader knows it: from its spec alone before its first poll, then from its
    latest Poll (``view_of``).  The output, the live view and the exporter keep one each."""

    spec: DeviceSpec
    state: str = UNKNOWN
    last_success: float | None = None
    last_poll: Poll | None = field(default=None)
    stats: PollStats = field(default=None, compare=False)

    def __init__(self, spec, state=UNKNOWN, last_success=None, last_poll=None, stats=None) -> None:
        # By hand, its fields one table: one a poll, made by each reader (codec/record.py says why).
        _device_view_fields(
            self,
            {
                "spec": spec,
                "state": state,
                "last_success": last_success,
                "last_poll": last_poll,
                "stats": stats,
            },
        )


_device_view_fields = fields_setter(DeviceView)


def view_of(poll: Poll) -> DeviceView:
    """The device as its latest poll left it: with groups, the latest value of every point."""
    stats = poll.stats if poll.stats is not None else PollStats()  # the scheduler's polls carry theirs
    if poll.latest is not None and poll.readings is not None:
        poll = poll._replace(readings=list(poll.latest))
    return DeviceView(poll.device, poll.state, poll.last_success, poll, stats)


def views(devices: list[DeviceSpec]) -> dict[str, DeviceView]:
    """Every device as a reader knows it before any poll: by name, in the inventory's order."""
    return {spec.name: DeviceView(spec, stats=PollStats()) for spec in devices}


@record
class Event:
    """A change of state: a device going offline or coming back, a link that cannot be opened."""

    time: float
    kind: str  # "device" or "link"
    name: str
    state: str
    reason: str = ""
    retry_in: float | None = None  # seconds to the next try, when it is backed off
    link: LinkView | None = field(default=None, compare=False)  # a link's event: the link then


class GroupState:
    """A group's clock: when it is next due, its polls, and how it has kept its interval."""

    def __init__(self, group: Group, now: float, grid: bool = False, paced: bool = False) -> None:
        self.group = group
        self.interval = group.interval
        # Its reader's read(execute), and its poll on its device's execute (``poll()``), bound
        # once by its worker: a poll reads them as attributes and calls them, where
        # group.reader.read(...) looked a record's field and a slot's callable up the generic way
        # every poll.
        self.read: Callable
        self.poll: Callable[[], Any]
        self.grid = grid  # its slots on a fixed grid (DeviceSpec.grid)
        self.due = now
        self.polls = 0
        self.last_round = math.inf  # its polls in the run (math.inf: until stopped); the worker's
        self.first = self.last = 0.0  # monotonic: when its first and its latest poll started
        self.overruns = 0
        self.overran = False  # an overrun counted since its worker last asked (LinkWorker._poll)
        self.skipped = 0  # slots of its grid passed while a poll ran over
        # How late after its slot a poll's start is noted (``started``): an overrun past LATE of
        # its interval; a grid's never (its passed slots are counted as skipped); every start
        # of a group of a device of groups, whose pace its records show (``pace``).
        self.noted_after = -math.inf if paced else math.inf if grid else LATE * self.interval
        # On a grid of no slots (--interval 0) it is always due: its polls go back to back.
        self.back_to_back = grid and not self.interval
        # The line's time of its longest read, on a serial line (plant/budget.py); 0: not known.
        # A read of it waits where it would make a faster group late (LinkWorker._held_for).
        self.line_time = 0.0
        # Its poll's ``execute`` on a link of several groups (LinkWorker: None on a link of one).
        self.cut_in: _CutIn | None = None

    @property
    def deadline(self) -> float:
        """When its poll should be done: its next slot (a read once: at once)."""
        return self.due + self.group.interval if self.group.interval < math.inf else self.due

    def started(self, now: float) -> None:
        """Its poll starts at ``now``, later than ``noted_after`` past its slot: an overrun if
        later than ``LATE`` of its interval (on a grid, a poll late is one whose slots passed:
        they are counted as skipped), and the start its pace runs from."""
        if not self.grid and now - self.due > LATE * self.interval:
            self.overruns += 1
            self.overran = True
        if not self.polls:
            self.first = now
        self.last = now

    def next(self, now: float) -> None:
        """The next slot of its interval; one that has passed already is skipped, not made up
        (an overrun: the poll took longer than its interval).  On a grid, the slots passed are
        counted as skipped (but after its last poll) and the next one waited for; else it is
        polled at once.  A grid of no slots (``back_to_back``) has no next slot: it stays due."""
        if self.back_to_back:
            return
        due = self.due + self.interval
        if due < now:
            interval = self.interval
            if not self.grid:
                self.overruns += 1
                self.overran = True
                due = now
            else:
                missed = math.ceil((now - due) / interval)
                due += missed * interval
                if not self.had():
                    self.skipped += missed
        self.due = due

    def had(self) -> bool:
        """Whether it has had the run's rounds (``--rounds``)."""
        return self.polls >= self.last_round

    def pace(self) -> Pace:
        achieved = (self.last - self.first) / (self.polls - 1) if self.polls > 1 else None
        return Pace(self.group.name, self.group.interval, achieved, self.polls, self.overruns)


class DeviceState:
    """What the scheduler knows of a device: when each of its groups is due, and how it has
    fared.  Its state is the device's, whichever group's poll settled it."""

    def __init__(self, spec: DeviceSpec, now: float) -> None:
        self.spec = spec
        self.groups = [GroupState(group, now, spec.grid, bool(spec.groups)) for group in spec.paced()]
        self.not_before = -math.inf  # offline: no group of it is polled before its back-off ends
        self.state = UNKNOWN
        self.failures = 0  # failed polls in a row
        # Offline, it is tried again by the one back-off rule: twice its interval, doubling.
        self.backoff = Backoff(min(2 * spec.fastest, spec.max_backoff), spec.max_backoff)
        self.last_success: float | None = None  # time.time()
        self.last_poll: Poll | None = None  # its latest published one (read --interval keeps its own)
        self.latest: dict[str, Reading] | None = {} if spec.groups else None  # each point's last reading
        self.stats = PollStats()
        # Its transactions' timeout and retries, where its polls are counted and how they read
        # (execute(request) on the link): made once by its worker, not a poll.
        self.limits: tuple[float, int]
        self.counted: Stats | DeviceAndLink
        self.execute: Callable

    @property
    def skipped(self) -> int:
        """Slots of its grid passed while a poll ran over (DeviceSpec.grid)."""
        return sum(group.skipped for group in self.groups)

    @property
    def due(self) -> float:
        """When a group of it is next due (not before its back-off ends)."""
        return max(self.not_before, min(group.due for group in self.groups))

    @due.setter
    def due(self, when: float) -> None:
        """Every group of it next due at ``when`` (math.inf: the run polls it no more)."""
        for group in self.groups:
            group.due = when

    @property
    def polls(self) -> int:
        """Its rounds: the polls of its group polled least (once every group has had its
        first, a group read once counts no more)."""
        groups = self.groups
        if len(groups) == 1:  # most devices: one group, whose polls they are
            return groups[0].polls
        repeated = [group.polls for group in self.groups if group.group.interval < math.inf]
        return min(repeated or [group.polls for group in self.groups])

    @polls.setter
    def polls(self, count: int) -> None:
        for group in self.groups:
            group.polls = count

    def answered(self, when: float) -> None:
        """A poll of it answered (its request left at ``when``): no failure in a row since."""
        self.failures = 0
        self.last_success = when

    def succeeded(self, now: float, when: float, group: GroupState | None = None) -> Event | None:
        """A poll (of ``group``: None, its first) answered: it keeps its slots, and is online."""
        self.answered(when)
        (group or self.groups[0]).next(now)
        was = self.state
        if was == ONLINE:
            return None
        self.state = ONLINE
        self.backoff.reset()  # only a device offline backed off
        self.not_before = -math.inf
        return Event(when, "device", self.spec.name, ONLINE) if was == OFFLINE else None

    def failed(
        self, now: float, when: float, reason: str, at_once: bool = False, group: GroupState | None = None
    ) -> Event | None:
        """A failed poll (of ``group``: None, its first); ``at_once``: offline now (its link
        cannot be opened).  Offline, the group that failed is tried again at the back-off's end
        and the others wait for it.  A device whose ``offline_after`` is 0 is never offline: it
        keeps its slots."""
        group = group or self.groups[0]
        self.failures += 1
        if not self.spec.offline_after:
            group.next(now)
            return None
        if self.state == OFFLINE:
            group.due = self.not_before = now + self.backoff.failed()
            return None
        if self.failures < self.spec.offline_after and not at_once:
            group.next(now)
            return None
        self.state = OFFLINE
        group.due = self.not_before = now + self.backoff.failed()
        return Event(when, "device", self.spec.name, OFFLINE, reason, self.backoff.wait)

    def last_slot(self, rounds: int) -> float:
        """When its last poll of ``rounds`` falls, its slots kept (offline: its next try, the
        later ones as uncertain as another offline device's)."""
        if self.state == OFFLINE:
            return self.due
        return max(
            group.due + max(0, rounds - group.polls - 1) * group.group.interval
            if group.group.interval < math.inf else group.due
            for group in self.groups
            if group.due < math.inf
        ) if self.due < math.inf else -math.inf  # fmt: skip


def _nothing() -> None:
    """A hook with nothing to do."""


class Stop(threading.Event):
    """The run's stop: an Event that says it was set by a plain attribute as well (``asked``),
    which a worker's loop reads every turn, where ``is_set()`` would be a call of Python's."""

    def __init__(self) -> None:
        super().__init__()
        self.asked = False

    def set(self) -> None:
        self.asked = True  # first: whoever the Event wakes sees it asked
        super().set()

    def clear(self) -> None:
        self.asked = False
        super().clear()


class Clock:
    """The scheduler's clocks: ``monotonic`` for its slots and back-offs, ``time`` for the
    records' stamps, and ``wait``, cut short when the run is stopped.  The tests give a fake
    one, and run a worker on its own thread with it (no socket, no sleep)."""

    monotonic = staticmethod(time.monotonic)
    sleep = staticmethod(time.sleep)  # the managed link's; a worker waits with ``wait``
    time = staticmethod(time.time)  # last: the module's name is the clock's from here on

    @staticmethod
    def wait(stop: Stop, seconds: float) -> None:
        stop.wait(seconds)


class LinkWorker:
    """One link's thread: its devices polled one transaction at a time."""

    def __init__(
        self,
        spec: LinkSpec,
        devices: list[DeviceState],
        report: Callable[[Poll | Event], None],
        stop: Stop,
        rounds: int = 0,
        trace=None,
        go: threading.Event | None = None,
        clock=Clock,
        open_link: Callable | None = None,
        backoff: Backoff | None = None,
        sent: Callable[[], None] | None = None,
        idle: Callable[[], None] | None = None,
        published: bool = True,
        timed: bool = True,
        answered: Callable[[float, Any], None] | None = None,
    ) -> None:
        """``open_link``: opens the link (a context manager giving a Client); None: the
        link's Connection, through link.connection.open_client.  ``backoff``: a failed link's
        (None: from its devices' intervals).  ``sent``: run when a poll's first request has
        left; ``idle``: when the worker is about to wait for a slot or a back-off, or its link
        is closed or keeps a --pause (what is held to show while the next request is on its
        way is shown now).  ``published``: its records go to readers on other threads, each
        with its own copy of the counts; not (one device, on the thread that reads them):
        none, and the link's counts are the device's.  ``timed``: its Polls carry their
        latency (not: read --interval of one request, whose round trip is its request's).
        ``answered``: an unpublished, untimed worker's: a poll that answered and changed nothing
        (its device online before and after, every point read) is handed to ``answered(when,
        readings)`` with no Poll made, as its Poll would say nothing more."""
        self.spec = spec
        self.clock = clock
        self.go = go  # set once every link's worker has started: none opens a link before
        self.devices = devices
        self.report = report
        self.stop = stop
        self.rounds = rounds  # 0: until stopped
        # --hex: the client's trace, made from its framer and a label naming the link and the
        # device being polled, for the trace lines of several links and devices to tell apart
        self.trace = trace
        self.polling = ""  # the device whose poll is under way
        # The link, opened when a device is due; one that cannot be opened is backed off by the
        # one rule, from twice its devices' shortest interval up to their longest max_backoff.
        traced = (lambda framer: trace(framer, label=self._label)) if trace else None
        if backoff is None:
            backoff = Backoff(
                min(2 * min(d.spec.fastest for d in devices), max(d.spec.max_backoff for d in devices))
                if devices
                else 0.0,
                max((d.spec.max_backoff for d in devices), default=0.0),
            )
        self.link = ManagedLink(
            open_link or (lambda: open_client(spec.connection, trace=traced)), backoff, clock=clock
        )
        self.sent, self.idle, self.published, self.timed = sent or _nothing, idle, published, timed
        assert answered is None or not (published or timed)  # else a Poll says more
        self.answered = answered
        self.state = UNKNOWN
        self.open_failures = 0  # times the link could not be opened
        self.stats = Stats()  # its devices' transactions, counted as they end
        self.accepted: dict[str, None] = {}  # deviations --lenient let through, each kind once
        self.stamp: float | None = None  # time.time() the poll under way's first request left
        self.sent_hook = self._request_sent  # bound once: the client's while_waiting, one a poll
        self.wall_time = clock.time  # a record's time
        self.monotonic = clock.monotonic  # a poll's end
        # Bound once, read as attributes: a worker has more attributes than an instance's
        # shared keys hold, and the interpreter leaves its method calls generic.
        self.settle, self.poll = self._settle, self._poll
        self.aimed: DeviceState | None = None  # the device the link is set for (_aim)
        self.reconnect_each, self.pause = False, 0.0  # the link's, read when the work starts
        self.follow_up = False
        self.after_each = (
            True  # every poll asks ``_after``, not only one that failed (read when the work starts)
        )
        # What each device's polls count in and read with, made once, not a poll.
        for device in devices:
            for group in device.groups:
                group.last_round = rounds or math.inf
            device.counted = DeviceAndLink(device.stats, self.stats) if published else self.stats
            device.execute = functools.partial(self.link.execute, device.spec.unit)  # execute(request)
        # The one group on the link, if it has one (a device of one group on a link of its own:
        # a TCP device, read --interval): no other's poll comes between its transactions, and
        # a turn of the loop has no other to choose.
        self.alone: tuple[DeviceState, GroupState] | None = None
        if sum(len(device.groups) for device in devices) == 1:
            self.alone = (devices[0], devices[0].groups[0])
        else:  # between the transactions of a group's poll, another due may cut in
            for device in devices:
                for group in device.groups:
                    group.cut_in = _CutIn(self, device, group)
        self.crashed: BaseException | None = None
        self.busy = 0.0  # seconds its polls took: what the line carries is its transactions in them
        # Whether it may yet say that it cannot keep up (``_overrun``): not once it has, nor where
        # every group is on a grid (its slots passed are skipped, not overruns).
        self.may_overrun = not all(group.grid for device in devices for group in device.groups)
        self.deadline: float | None = None  # monotonic: when the run ends (--duration)
        # Work handed in (poll --mqtt's writes), done by this thread between polls: None until
        # accept_jobs, and the link is then never opened a second time for it.
        self.jobs: queue.SimpleQueue | None = None
        self.poke = threading.Event()
        self.thread = threading.Thread(target=self.run, name=f"link {spec.name}", daemon=True)
        if serial_line(spec.connection) and self.alone is None:  # alone, a read waits for no other
            for device in devices:
                for group in device.groups:
                    group.line_time = max(
                        (transaction_seconds(spec.connection, device.spec.unit, block.request)
                         for block in group.group.reader.blocks),
                        default=0.0,
                    )  # fmt: skip
        # That it moves, for systemd's watchdog (Plant.moved): its loop's turns, and whether it
        # waits on schedule for its next poll.
        self.turns = 0
        self.asleep = False

    def accept_jobs(self) -> None:
        self.jobs = queue.SimpleQueue()

    def submit(self, device: str, job: Callable) -> None:
        """``job(execute)`` run on this thread before its next poll: ``execute(request)`` is one
        transaction with ``device`` on the link's ManagedLink, with the device's timeout and
        retries; None when the link is not open (it is not opened for a job: its devices' polls
        open it, by the back-off rule)."""
        assert self.jobs is not None  # accept_jobs() made the queue
        self.jobs.put((device, job))
        self.poke.set()

    def _run_jobs(self) -> None:
        assert self.jobs is not None  # accept_jobs() made the queue
        while not self.jobs.empty():
            device, job = self.jobs.get_nowait()
            link = self.link
            if link.client is None:
                job(None)
                continue
            spec = next(d.spec for d in self.devices if d.spec.name == device)
            self.polling = spec.name  # --hex's label
            link.client.timeout, link.client.retries = limits(spec, self.spec)
            link.stats = None  # a job is no poll: the device's and link's counts stay its polls'
            self.aimed = None
            job(functools.partial(link.execute, spec.unit))

    def _sleep(self, seconds: float) -> None:
        """Until the next poll, the run's stop, or (with jobs) a job handed in."""
        self.asleep = True
        if self.jobs is None:
            self.clock.wait(self.stop, seconds)
        else:  # in short slices, so that the run's stop is seen as soon as without jobs
            self.clock.wait(self.poke, min(seconds, 0.2))
            self.poke.clear()
        self.asleep = False

    def limits(self) -> list[tuple[float, int]]:
        """The timeout and retries of each of its devices' transactions."""
        return [limits(d.spec, self.spec) for d in self.devices]

    def finished(self) -> bool:
        """--once, --rounds: every device has had its polls, or will be tried no more."""
        return bool(self.rounds) and not self._waiting()

    def _next_due(self) -> float:
        """When a group of its devices is next due (math.inf: none will be; a device that has
        had its rounds is due never)."""
        alone = self.alone
        if alone is not None:
            return alone[1].due  # never before its device's back-off ends (_earliest)
        return min(device.due for device in self.devices)

    def _waiting(self) -> list[DeviceState]:
        """The devices this run will poll again."""
        return [d for d in self.devices if d.due < math.inf and not (self.rounds and d.polls >= self.rounds)]

    def _tried_again(self, device: DeviceState) -> bool:
        """Whether the run will last until ``device`` is due again: never past its rounds or
        its deadline; with rounds, an offline device only where its back-off ends before the
        last poll the link's other devices have still to make.  A device that will not be is
        done (due never), so the run does not wait for it."""
        others = [d for d in self._waiting() if d is not device]
        if self.rounds:
            if device.polls >= self.rounds:
                return False
            if device.state == OFFLINE:
                # The last slot of each other device, or the next try of an offline one (its
                # later tries are as uncertain as this one's).
                last = max((d.last_slot(self.rounds) for d in others), default=-math.inf)
                if device.due > last:
                    device.due = math.inf
                    return False
        return self.deadline is None or device.due < self.deadline

    def run(self) -> None:
        try:
            if self.go is not None:
                self.go.wait()
            self._work()
        except BaseException as error:  # a bug: the plant stops, and says so on the main thread
            self.crashed = error
            self.stop.set()
        finally:
            self.link.close()

    def work(self) -> None:
        """Poll on this thread until the run is over or stopped; what ends it (Ctrl-C, a
        request the link cannot carry, the output failing) is raised, with the link closed."""
        try:
            self._work()
        finally:
            self.link.close()

    def _due(self, now: float, before: float = math.inf) -> list[tuple[DeviceState, GroupState]]:
        """The groups due now (whose deadline is before ``before``), the earliest deadline first:
        a group's deadline is its next slot, so of two groups due the faster goes first, and of
        two of one pace the one that has waited longest."""
        due = [
            (device, group)
            for device in self._waiting()
            if device.not_before <= now
            for group in device.groups
            if group.due <= now and group.deadline < before and not group.had()
        ]
        return sorted(due, key=lambda pair: pair[1].deadline)

    def _earliest(self, now: float) -> tuple[DeviceState, GroupState] | None:
        """The first of ``_due(now)``, found without building the list: the group a turn of the
        loop polls."""
        # A device that has had its rounds has every group due never (_settle, _open).
        alone = self.alone
        if alone is not None:
            # No other to choose, and its due is never before its device's back-off ends
            # (DeviceState.failed, _open) nor after its rounds (_settle): it is all there is to ask.
            return alone if alone[1].due <= now else None
        earliest = None
        for device in self.devices:
            if device.not_before > now:
                continue
            for group in device.groups:
                if group.due <= now and not group.had():
                    # deadlines compared only when two are due: one alone is polled
                    if earliest is None or group.deadline < earliest[1].deadline:
                        earliest = (device, group)
        return earliest

    def _held_for(self, now: float, group: GroupState) -> float | None:
        """When a group with an earlier deadline than ``group``'s falls due before ``group``'s
        next read would end on the line: then (the read waits for it, which goes first), else
        None.  A read is held back only while less than ``LATE`` of its own interval late: fast
        groups that leave the line no gap long enough do not starve it."""
        if not group.line_time or now - group.due >= LATE * group.group.interval:
            return None
        ends = now + group.line_time
        soon = [
            other.due
            for device in self._waiting()
            if device.not_before < ends
            for other in device.groups
            if now < other.due < ends and other.deadline < group.deadline and not other.had()
        ]
        return min(soon, default=None)

    def _work(self) -> None:
        # What every poll asks of the settings, read once: each device's timeout and retries,
        # and --reconnect-each and --pause, which decide what follows a poll.
        for device in self.devices:
            device.limits = limits(device.spec, self.spec)
            for group in device.groups:
                reader = group.group.reader
                group.read = reader.read
                # One request's poll is its transaction, a partial of the device's (itself one
                # of the link's execute): made in C, with no frame of Python's a poll.
                group.poll = (
                    functools.partial(reader.read, device.execute)
                    if reader.request is None
                    else functools.partial(device.execute, reader.request)
                )
        self.reconnect_each, self.pause = self.spec.connection.reconnect_each, self.spec.connection.pause
        self.follow_up = self.reconnect_each or bool(self.pause)  # something follows every poll
        self.after_each = self.spec.connection.lenient or self.follow_up
        if self.alone is not None and self.jobs is None:
            self._work_alone(*self.alone)
            return
        link, clock, stop, poll = self.link, self.clock, self.stop, self.poll
        # A turn goes back by an unconditional jump, the stop asked at its start: Python 3.11
        # specializes a function's reads once it has been called or jumped back that way a few
        # times, and a while's test jumping back does not count: this function, called once a
        # run, would have read every attribute of every turn the generic way.
        while True:
            if stop.asked:
                return
            self.turns += 1
            if self.jobs is not None:
                self._run_jobs()
            now = clock.monotonic()
            if link.client is not None:
                ready_at = -math.inf
                due = self._earliest(now)
            else:
                ready_at = link.ready_at
                due = self._earliest(now) if ready_at <= now else None
            if due is None:
                if self._rest(now, max(self._next_due(), ready_at)) is None:
                    return
                continue
            device, group = due
            if group.line_time:
                held = self._held_for(now, group)
                if held is not None:  # a faster group falls due before this read would end
                    self._sleep(held - now)
                    continue
            client = link.client
            if client is None:
                now, client = self._reopen(device, now)
                if client is None:
                    continue
            poll(device, group, now, client)

    def _work_alone(self, device: DeviceState, group: GroupState) -> None:
        """``_work`` for a link of one group and no jobs (a TCP device of its own, read
        --interval): a turn asks only whether its one group is due (never before its device's
        back-off ends, nor after its rounds) and its link open."""
        link, monotonic, stop, poll = self.link, self.monotonic, self.stop, self.poll
        # A turn's time is when the one before ended: a poll's end, a rest's waking, an open's end.
        now = monotonic()
        while True:  # not ``while not stop.asked``, as _work's
            if stop.asked:
                return
            self.turns += 1
            client = link.client
            due = group.due
            if due > now:  # its next slot; a link that is not open, ready to open again no sooner
                woke = self._rest(now, due if client is not None else max(due, link.ready_at))
                if woke is None:
                    return
                now = woke
                continue
            if client is None:
                ready_at = link.ready_at
                if ready_at > now:
                    woke = self._rest(now, ready_at)
                    if woke is None:
                        return
                    now = woke
                    continue
                now, client = self._reopen(device, now)
                if client is None:
                    continue
            now = poll(device, group, now, client)

    def _rest(self, now: float, wake: float) -> float | None:
        """No group due at ``now``: wait until ``wake``, when the next is due or the link is ready
        to open again, whichever is later (math.inf: none will be).  The time it woke (monotonic);
        None: the run is over."""
        if wake == math.inf and self.finished():
            return None
        if self.idle is not None:
            self.idle()
        # a minute at most: a device whose every point is read once waits for a reconnect
        self._sleep(min(max(0.0, wake - now), 60.0))
        return self.clock.monotonic()

    def _reopen(self, device: DeviceState, now: float) -> tuple[float, Client | None]:
        """The link opened for ``device``'s poll due at ``now``: the time then and its client
        (None: it could not be)."""
        opened = self._open(self._due(now))
        now = self.clock.monotonic()
        if not opened:
            return now, None
        client = self.link.client
        assert client is not None  # opened
        if device.spec.grid and not device.polls:
            # The grid starts with the first link open: opening sim:// (its imports) or a slow
            # handshake is not a poll overrunning its slot.  What the first link made stays as
            # long as the run: the collector need not walk it again.
            gc.freeze()
            device.due = now
        return now, client

    def _open(self, due: list[tuple[DeviceState, GroupState]]) -> bool:
        try:
            self.link.open()
        except FATAL:
            raise
        except (*KNOWN_ERRORS, OSError) as error:
            error = link_failure(error)  # its devices' polls fail with it: exit 6, not 1
            reason = str(error)
            when = self.clock.time()
            first = self.state != OFFLINE
            self.state = OFFLINE
            self.open_failures += 1
            settled: list[Poll | Event] = []
            for device, group in due:  # its devices cannot be reached: offline meanwhile
                # Each poll's request could not go: a transaction with no connection, counted
                # as ping and read --interval count it.
                DeviceAndLink(device.stats, self.stats).transaction(error, 0)
                now = self.clock.monotonic()
                group.started(now)
                self._settle(
                    settled.append, device, group, None, error, when, now, not_before=self.link.ready_at
                )
            # Opened again only for a device the run will still poll, and before its end.
            again = any(self.deadline is None or d.due < self.deadline for d in self._waiting())
            if first:
                retry_in = self.link.backoff.wait if again else None
                self.report(Event(when, "link", self.spec.name, OFFLINE, reason, retry_in, self.view()))
            for item in settled:
                self.report(item)
            return False
        if self.state == OFFLINE:
            self.state = ONLINE
            self.report(Event(self.clock.time(), "link", self.spec.name, ONLINE, link=self.view()))
        self.state = ONLINE
        self.aimed = None  # a new link: set for each device's transactions anew
        if self.link.opens > 1:  # a reconnect: what is read once is read again
            now = self.clock.monotonic()
            for device in self._waiting():  # not of a device that has had its rounds
                for group in device.groups:
                    if group.group.interval == math.inf and not group.had():
                        group.due = now
        return True

    def view(self) -> LinkView:
        """The link as it is now, for a record: its own copy of the counts."""
        return LinkView(self.spec.name, self.state, self.open_failures, self.stats.copy())

    def _label(self) -> str:
        return f"{self.spec.name} {self.polling}".rstrip()

    def _request_sent(self) -> None:
        """Run by the client right after a poll's first request has left: that is the poll's
        time."""
        # Read as attributes, then called: a method call of an instance's attribute is looked
        # up the generic way every poll.
        wall_time, sent = self.wall_time, self.sent
        self.stamp = wall_time()
        sent()

    def _aim(self, device: DeviceState, client) -> None:
        """The link (its ``client``) set for ``device``'s transactions: one transaction at a time
        on a link.  It stays so for the device's next poll, unless the link or a job changed it
        (``aimed``)."""
        self.polling = device.spec.name
        client.timeout, client.retries = device.limits
        self.link.stats = device.counted
        self.aimed = device

    def _poll(
        self, device: DeviceState, group: GroupState, began: float, client: Client, nested: bool = False
    ) -> float:
        """One poll of ``group``, a group of ``device``, begun at ``began`` (monotonic), on the
        link's open ``client``; the time it ended (monotonic).  On a link of several groups, a
        group due with an earlier deadline is polled between its transactions (``_CutIn``)."""
        if began - group.due > group.noted_after:  # late for its slot, or a start its pace counts
            group.started(began)
        self.stamp = None
        client.while_waiting = self.sent_hook  # its first request out: the poll's time
        if self.aimed is not device:
            self._aim(device, client)
        cut_in = group.cut_in
        untimed = self.stats.untimed  # every reply of the poll timed: as many untimed after it
        error: BaseException | None = None
        latency: float | None = None
        try:
            if cut_in is None or nested:  # no other's poll comes between its transactions
                poll = group.poll
                readings = poll()
                if self.timed and self.stats.untimed == untimed:
                    latency = client.replied_at - client.work_sent_at
            else:
                read = group.read
                readings = read(cut_in.execute)
                if self.timed and self.stats.untimed == untimed and not cut_in.happened:  # its own
                    latency = client.replied_at - client.work_sent_at
        except PartialRead as partial:
            readings, error = partial.readings, partial
            self.aimed = None  # a link lost midway was opened again, as it is, by the next read
        except FATAL:
            raise
        except (*KNOWN_ERRORS, OSError) as failure:
            readings, error = None, link_failure(failure)  # a lost link the managed link closed
            client.while_waiting = None  # the request never left, perhaps: no later one runs it
            self.aimed = None  # a new link next poll, set for its device then
        monotonic = self.monotonic
        ended = monotonic()
        when = self.stamp
        if when is None:  # the request never left
            when = self.wall_time()
        settle = self.settle
        settle(self.report, device, group, readings, error, when, ended, latency)
        if self.may_overrun:
            if not nested:  # a poll cut in is in the time of the one it cut into
                self.busy += ended - began
            if group.overran:
                group.overran = False
                self._overrun()
        if self.after_each or error is not None:
            self._after(client, error is not None, nested)
            ended = monotonic()  # what follows a poll may wait (the output, shown while idle)
        return ended

    def _after(self, client: Client, failed: bool, nested: bool) -> None:
        """What follows a poll (on ``client``) that failed, or every poll of a link with
        --lenient (the deviations it let through, collected), --reconnect-each or --pause."""
        if client.deviations:  # --lenient took a reply as it was: the summary says so
            self.accepted.update(client.deviations)
        # A poll that failed may have lost the link (only a failed one can).
        if (failed or self.follow_up) and not nested:
            self._follow_up()

    def _follow_up(self) -> None:
        """What follows a poll that failed, or every poll of a link with --reconnect-each or
        --pause: the link dropped, and what is held to show shown before the next request."""
        link = self.link
        if self.reconnect_each and link.client is not None:
            # --reconnect-each: a new link every poll, for devices and gateways that serve one
            # client or leak connections; no wait, as nothing failed.
            link.drop(on_purpose=True)
        if self.idle is not None and (link.client is None or self.pause):
            self.idle()  # a new link or a pause comes before the next request

    def asked(self) -> float:
        """The reads a second its devices' groups ask (an offline device's none)."""
        return sum(
            len(group.group.reader.blocks) / group.group.interval
            for device in self.devices
            if device.state != OFFLINE
            for group in device.groups
        )

    def _overrun(self) -> None:
        """A group's poll overran (it started late, or took longer than its interval): when what
        its groups ask is more than the link has carried while busy, that is why, and it is said
        once, with the figures."""
        if not self.busy:
            return
        asked, carried = self.asked(), self.stats.transactions / self.busy
        if asked > carried:
            self.may_overrun = False
            reason = f"asked {asked:.1f} reads/s, the line carries {carried:.1f}"
            self.report(Event(self.clock.time(), "link", self.spec.name, OVERRUN, reason, link=self.view()))

    def _settle(
        self,
        report: Callable[[Poll | Event], None],
        device: DeviceState,
        group: GroupState,
        readings,
        error,
        when: float,
        now: float,
        latency: float | None = None,
        not_before: float | None = None,
    ) -> None:
        """A poll of ``group`` that ended at ``now`` (monotonic) in the device's state: its Poll,
        and the Event of its change of state if it had one, handed to ``report``.  ``not_before``:
        its link cannot be opened, so the device is offline now and not tried before the link is."""
        polls = group.polls = group.polls + 1
        # (a partial read answered: the device is there)
        if readings is not None and device.state == ONLINE:  # it answered, and stays online
            device.answered(when)  # DeviceState.succeeded with no change of state
            if not group.back_to_back:  # (which has no next slot: GroupState.next)
                group.next(now)
            if polls >= group.last_round:  # it has had its rounds (GroupState.had)
                group.due = math.inf
            answered = self.answered
            if answered is not None and error is None:  # its time and readings are all it says
                answered(when, readings)
                return
            event = None
        else:
            event = self._changed(device, group, readings is not None, error, when, now, not_before)
        if not self.published:  # read on this thread, before the next poll: nothing to copy
            # fmt: off
            report(_poll_of((
                device.spec, when, readings, error, device.state, device.last_success,
                None, None, DEFAULT, None, None, latency,
            )))
            # fmt: on
            if event is not None:
                report(event)
            return
        ok = readings is not None
        device.stats.poll(ok)
        latest = None
        if device.latest is not None and ok:
            device.latest.update((reading.point.name, reading) for reading in readings)
            latest = tuple(device.latest.values())
        poll = _poll_of(
            (
                device.spec,
                when,
                readings,
                error,
                device.state,
                device.last_success,
                device.stats.copy(),
                self.view(),
                group.group.name,
                None if device.latest is None else group.pace(),  # a device of groups' (latest)
                latest,
                latency,
            )
        )
        device.last_poll = poll
        report(poll)
        if event is not None:
            report(event)

    def _changed(
        self,
        device: DeviceState,
        group: GroupState,
        ok: bool,
        error,
        when: float,
        now: float,
        not_before: float | None,
    ) -> Event | None:
        """``_settle`` of a poll that failed, or that answered a device not online: the device's
        next try, and the Event of its change of state if it had one."""
        if ok:
            event = device.succeeded(now, when, group)
        else:
            event = device.failed(now, when, str(error), not_before is not None, group)
            if not_before is not None and device.state == OFFLINE:
                device.not_before = max(device.not_before, not_before)
                group.due = max(group.due, not_before)
        if group.polls >= group.last_round:  # it has had its rounds (GroupState.had)
            group.due = math.inf
        # Whether it will be tried again matters to an event's announcement, and decides an
        # offline device's next try; a device that answered is polled again while the run lasts.
        if (event is not None or device.state == OFFLINE) and not self._tried_again(device):
            if event is not None and event.retry_in is not None:
                event = replace(event, retry_in=None)  # the run ends first: no next try to announce
        return event


class _CutIn:
    """A group's ``execute`` on a link of several groups: before each transaction of its poll
    but the first, a group due with an earlier deadline is polled first (not cut into itself),
    so a fast group is never held up by more than one transaction of a slow group's long read,
    and on a serial line not even by that (``LinkWorker._held_for``)."""

    __slots__ = ("worker", "device", "group", "client", "happened")

    def __init__(self, worker: LinkWorker, device: DeviceState, group: GroupState) -> None:
        self.worker, self.device, self.group = worker, device, group
        self.client: Any = None  # the link's client when its poll's first transaction began
        # Another group's poll came between its poll's transactions: its latency is not its own.
        self.happened = False

    def execute(self, request):
        worker, device, group = self.worker, self.device, self.group
        stamp = worker.stamp
        if stamp is None:  # its poll's first request has yet to leave
            self.client, self.happened = worker.link.client, False
        else:
            clock = worker.clock
            held = worker._held_for(clock.monotonic(), group)
            if held is not None:  # the next read would make a faster group late: it goes first
                clock.wait(worker.stop, held - clock.monotonic())
            others = worker._due(clock.monotonic(), before=group.deadline)
            for other, other_group in others:
                client = worker.link.client
                assert client is not None  # a group is polled on an open link
                worker._poll(other, other_group, clock.monotonic(), client, nested=True)
            if others:
                self.happened = True
                if worker.link.client is not self.client:  # lost by the other's poll: this one ends too
                    raise ConnectionFailed(f"link {worker.spec.name} was lost")
                worker.stamp = stamp
                worker._aim(device, self.client)
        return device.execute(request)


class Plant:
    """Every link's worker, started together; ``run`` returns when they are done or stopped."""

    def __init__(
        self,
        links: dict[str, LinkSpec],
        devices: list[DeviceSpec],
        report: Callable[[Poll | Event], None],
        rounds: int = 0,
        trace=None,
        traced: Collection[str] | None = None,
    ) -> None:
        """``trace``: --hex's, for the links ``traced`` names (None: every link).  ``report``
        is called on the thread that calls ``run``, with each record as the workers publish it."""
        self.report = report
        self.records: queue.SimpleQueue[Poll | Event] = queue.SimpleQueue()
        self.stop = Stop()
        self.go = threading.Event()
        self.ended = False  # its duration ran out
        self.start_within = START_WITHIN
        self.handed = 0  # records handed to ``report``
        self.last_seen: tuple | None = None  # what ``moved`` saw last
        now = time.monotonic()
        self.devices = {spec.name: DeviceState(spec, now) for spec in devices}
        self.workers = [
            LinkWorker(
                spec,
                [state for state in self.devices.values() if state.spec.link == name],
                self.records.put,
                self.stop,
                rounds,
                trace if traced is None or name in traced else None,
                self.go,
            )
            for name, spec in links.items()
        ]
        self.workers = [worker for worker in self.workers if worker.devices]

    def completed(self) -> bool:
        """The run ended as it was to end: every round polled, or its duration over."""
        return self.ended or (bool(self.workers) and all(worker.finished() for worker in self.workers))

    def run(self, duration: float | None = None) -> None:
        deadline = None if duration is None else time.monotonic() + duration
        for worker in self.workers:
            worker.deadline = deadline
        self._start_workers()
        self.go.set()
        try:
            while any(worker.thread.is_alive() for worker in self.workers):
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    self.ended = True
                    self.stop.set()
                    left = None
                # Short waits: Ctrl-C reaches this thread between them.
                self._publish(0.2 if left is None else min(0.2, left))
        except KeyboardInterrupt:
            self._end()
            self._publish()  # the polls the workers ended as they stopped
            raise
        except BaseException:
            self._end()  # the output failed: nothing more can be shown
            raise
        self._end()
        self._publish()
        for worker in self.workers:
            if worker.crashed is not None:
                raise worker.crashed

    def moved(self) -> bool:
        """Whether the plant has moved since the last call (systemd's watchdog asks, from its own
        thread): the thread that runs it handed on records, or had none waiting at either call;
        and each link's worker turned its loop, waits on schedule for its next poll, or is done.
        A worker that neither turned nor waited at both calls is stuck in its work, and records
        waiting at both, none handed, are stuck in the output (a pipe nobody reads)."""
        waiting = not self.records.empty()
        seen = (self.handed, waiting, [(w.turns, w.asleep) for w in self.workers])
        last, self.last_seen = self.last_seen, seen
        if last is None:
            return True
        output = seen[0] != last[0] or not (waiting and last[1])
        links = all(
            now != before or now[1] or before[1] or not worker.thread.is_alive()
            for worker, now, before in zip(self.workers, seen[2], last[2], strict=True)
        )
        return output and links

    def _start_workers(self) -> None:
        """Every worker's thread started, each within ``start_within`` seconds; ConnectionFailed (exit
        6, one line) if the system refuses one.  Started by a thread of their own: Thread.start
        waits with no deadline for the new thread to say it began, and a thread that dies in its
        start-up (MemoryError under a capped address space) never says so.  A starter stuck so
        is left behind; a thread of ``_thread``'s, the interpreter does not wait for it at exit."""
        started: list[LinkWorker] = []
        refused: list[BaseException] = []
        done = threading.Event()

        def start_each() -> None:
            try:
                for worker in self.workers:
                    worker.thread.start()
                    started.append(worker)
            except Exception as error:  # "can't start new thread", MemoryError: the system's limits
                refused.append(error)
            finally:
                done.set()

        try:
            _thread.start_new_thread(start_each, ())
        except Exception as error:
            refused.append(error)
        else:
            # A deadline a thread, not for them all: a plant of thousands of links on a loaded
            # machine starts them for longer, but never waits on one for ``start_within``.
            count = 0
            while not done.wait(self.start_within):
                if len(started) == count:
                    refused.append(TimeoutError(f"a thread did not start within {self.start_within:g} s"))
                    break
                count = len(started)
        if refused:
            # Said before any link is opened: those started wait for ``go``, see the stop, and end.
            self.stop.set()
            self.go.set()
            for each in list(started):
                each.thread.join(self.start_within)
            raise ConnectionFailed(
                f"cannot start a worker for each link: {len(started)} of {len(self.workers)} links "
                f"started before the system refused a thread ({str(refused[0]) or type(refused[0]).__name__}); "
                "poll fewer links a process, or raise its limits (ulimit -v, -u)"
            )

    def _publish(self, wait: float | None = None) -> None:
        """Hand every record the workers have published to ``report``, on this thread; with
        ``wait``, wait that long for the first one (None: take only those already there)."""
        try:
            item = self.records.get(timeout=wait) if wait is not None else self.records.get_nowait()
        except queue.Empty:
            return
        while True:
            self.report(item)
            self.handed += 1
            try:
                item = self.records.get_nowait()
            except queue.Empty:
                return

    def _end(self) -> None:
        """Stop the workers and wait for them: each ends its poll's transaction first, at most a
        timeout a try."""
        self.stop.set()
        for worker in self.workers:
            longest = max(timeout * (retries + 1) for timeout, retries in worker.limits())
            worker.thread.join(longest + 1)
