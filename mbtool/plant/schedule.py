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
worker is about to wait).  A request the link cannot carry (``RequestError``), an output that
failed and a reader of stdout gone end the run: no later poll can do better.

A run that ends (``rounds``, a duration) makes no promise it cannot keep: a back-off that
would end after the run is announced without its next try.  With ``rounds`` a device is done
once polled that many times, and an offline one is tried again only where its back-off ends
before the last poll the link's other devices still have to make: so every device that
answers gets its rounds, an offline one fewer, and the run does not wait out a back-off.
"""

from __future__ import annotations

import functools
import gc
import math
import operator
import queue
import threading
import time
from collections.abc import Callable, Collection
from typing import Any, Protocol

from mbtool.codec.errors import RequestError
from mbtool.codec.record import field, record, replace
from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, OutputFailed, PartialRead, link_failure
from mbtool.link.connection import Connection, open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats
from mbtool.plant.stats import DeviceAndLink, PollStats, copy_stats
from mbtool.registermap.plan import Reading

ONLINE, OFFLINE, UNKNOWN = "online", "offline", "unknown"


class Reader(Protocol):
    """What a device's poll reads, given ``execute(request)`` on its link: a register map's
    points (``MapReader``), or read --interval's request or requests."""

    def read(self, execute: Callable) -> Any: ...


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
    # Its slots on a fixed grid from its first poll (read --interval): one that has passed is
    # skipped and counted, and the next slot of the grid waited for; else (a plant) a device
    # late for its slot is polled at once, and its interval runs from there.
    grid: bool = False


# What ends a run rather than fails a poll: a request the link cannot carry (no later poll can
# do better), the output that failed, and stdout's reader gone.
FATAL = (RequestError, OutputFailed, BrokenPipeError)


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


@record
class Poll:
    """One device poll: its readings (all, or some with PartialRead as ``error``), or the
    error that kept it from reading any."""

    device: DeviceSpec
    time: float  # time.time(): when its first request went out, or when it failed
    readings: list[Reading] | None
    error: BaseException | None
    state: str  # the device's state after the poll
    # The device and its link as the poll left them, copies no later poll changes: what a
    # reader shows of them comes from here, never from the link thread's own state.
    last_success: float | None = field(default=None, compare=False)  # time.time()
    stats: PollStats | None = field(default=None, compare=False)
    link: LinkView | None = field(default=None, compare=False)
    # From its first request leaving to its last reply; None: a reply of it came untimed (while
    # mbtool was busy) or it failed.
    latency: float | None = field(default=None, compare=False)

    def __init__(
        self, device, time, readings, error, state, last_success=None, stats=None, link=None, latency=None
    ) -> None:
        # By hand: one a poll (codec/record.py says why).
        fields = self.__dict__
        fields["device"] = device
        fields["time"] = time
        fields["readings"] = readings
        fields["error"] = error
        fields["state"] = state
        fields["last_success"] = last_success
        fields["stats"] = stats
        fields["link"] = link
        fields["latency"] = latency


@record
class LinkView:
    """A link as its thread saw it when it published a record: its state, the opens that failed
    and its devices' transactions."""

    name: str
    state: str
    open_failures: int
    stats: Stats = field(compare=False)


@record
class DeviceView:
    """A device as a reader knows it: from its spec alone before its first poll, then from its
    latest Poll (``view_of``).  The output, the live view and the exporter keep one each."""

    spec: DeviceSpec
    state: str = UNKNOWN
    last_success: float | None = None
    last_poll: Poll | None = field(default=None)
    stats: PollStats = field(default=None, compare=False)


def view_of(poll: Poll) -> DeviceView:
    """The device as its latest poll left it."""
    stats = poll.stats if poll.stats is not None else PollStats()  # the scheduler's polls carry theirs
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


class DeviceState:
    """What the scheduler knows of a device: when it is due, and how it has fared."""

    def __init__(self, spec: DeviceSpec, now: float) -> None:
        self.spec = spec
        self.due = now
        self.state = UNKNOWN
        self.failures = 0  # failed polls in a row
        # Offline, it is tried again by the one back-off rule: twice its interval, doubling.
        self.backoff = Backoff(min(2 * spec.interval, spec.max_backoff), spec.max_backoff)
        self.polls = 0
        self.skipped = 0  # slots of its grid passed while a poll ran over (DeviceSpec.grid)
        self.rounds = 0  # its polls in the run (0: until stopped); the worker's
        # Its transactions' timeout and retries, where its polls are counted and how they read
        # (execute(request) on the link): made once by its worker, not a poll.
        self.limits: tuple[float, int]
        self.counted: Stats | DeviceAndLink
        self.execute: Callable
        self.last_success: float | None = None  # time.time()
        self.last_poll: Poll | None = None
        self.stats = PollStats()

    def succeeded(self, now: float, when: float) -> Event | None:
        self.failures = 0
        self.last_success = when
        self._next(now)
        was = self.state
        if was == ONLINE:
            return None
        self.state = ONLINE
        self.backoff.reset()  # only a device offline backed off
        return Event(when, "device", self.spec.name, ONLINE) if was == OFFLINE else None

    def failed(self, now: float, when: float, reason: str, at_once: bool = False) -> Event | None:
        """A failed poll; ``at_once``: offline now (its link cannot be opened).  A device whose
        ``offline_after`` is 0 is never offline: it keeps its slots."""
        self.failures += 1
        if not self.spec.offline_after:
            self._next(now)
            return None
        if self.state == OFFLINE:
            self.due = now + self.backoff.failed()
            return None
        if self.failures < self.spec.offline_after and not at_once:
            self._next(now)
            return None
        self.state = OFFLINE
        self.due = now + self.backoff.failed()
        return Event(when, "device", self.spec.name, OFFLINE, reason, self.backoff.wait)

    def _next(self, now: float) -> None:
        """The next slot of its interval; one that has passed already is skipped, not made up:
        on a grid, the slots passed are counted (but after its last poll) and the next one
        waited for; else it is polled at once."""
        interval = self.spec.interval
        self.due += interval
        if self.due < now:
            if self.spec.grid and interval > 0:
                missed = math.ceil((now - self.due) / interval)
                self.due += missed * interval
                if not (self.rounds and self.polls >= self.rounds):
                    self.skipped += missed
            else:
                self.due = now


class Clock:
    """The scheduler's clocks: ``monotonic`` for its slots and back-offs, ``time`` for the
    records' stamps, and ``wait``, cut short when the run is stopped.  The tests give a fake
    one, and run a worker on its own thread with it (no socket, no sleep)."""

    monotonic = staticmethod(time.monotonic)
    sleep = staticmethod(time.sleep)  # the managed link's; a worker waits with ``wait``
    time = staticmethod(time.time)  # last: the module's name is the clock's from here on

    @staticmethod
    def wait(stop: threading.Event, seconds: float) -> None:
        stop.wait(seconds)


_DUE = operator.attrgetter("due")  # when a device is due: the scheduler's order


class LinkWorker:
    """One link's thread: its devices polled one transaction at a time."""

    def __init__(
        self,
        spec: LinkSpec,
        devices: list[DeviceState],
        report: Callable[[Poll | Event], None],
        stop: threading.Event,
        rounds: int = 0,
        trace=None,
        go: threading.Event | None = None,
        clock=Clock,
        open_link: Callable | None = None,
        backoff: Backoff | None = None,
        sent: Callable[[], None] | None = None,
        idle: Callable[[], None] | None = None,
        published: bool = True,
    ) -> None:
        """``open_link``: opens the link (a context manager giving a Client); None: the
        link's Connection, through link.connection.open_client.  ``backoff``: a failed link's
        (None: from its devices' intervals).  ``sent``: run when a poll's first request has
        left; ``idle``: when the worker is about to wait for a slot or a back-off, or its link
        is closed or keeps a --pause (what is held to show while the next request is on its
        way is shown now).  ``published``: its records go to readers on other threads, each
        with its own copy of the counts; not (one device, on the thread that reads them):
        none, and the link's counts are the device's."""
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
                min(2 * min(d.spec.interval for d in devices), max(d.spec.max_backoff for d in devices))
                if devices
                else 0.0,
                max((d.spec.max_backoff for d in devices), default=0.0),
            )
        self.link = ManagedLink(
            open_link or (lambda: open_client(spec.connection, trace=traced)), backoff, clock=clock
        )
        self.sent, self.idle, self.published = sent, idle, published
        self.state = UNKNOWN
        self.open_failures = 0  # times the link could not be opened
        self.stats = Stats()  # its devices' transactions, counted as they end
        self.accepted: dict[str, None] = {}  # deviations --lenient let through, each kind once
        self.stamp: float | None = None  # time.time() the poll under way's request left
        self.reconnect_each, self.pause = False, 0.0  # the link's, read when the work starts
        # What each device's polls count in and read with, made once, not a poll.
        for device in devices:
            device.rounds = rounds
            device.counted = DeviceAndLink(device.stats, self.stats) if published else self.stats
            device.execute = functools.partial(self.link.execute, device.spec.unit)  # execute(request)
        self.crashed: BaseException | None = None
        self.deadline: float | None = None  # monotonic: when the run ends (--duration)
        # Work handed in (poll --mqtt's writes), done by this thread between polls: None until
        # accept_jobs, and the link is then never opened a second time for it.
        self.jobs: queue.SimpleQueue | None = None
        self.poke = threading.Event()
        self.thread = threading.Thread(target=self.run, name=f"link {spec.name}", daemon=True)

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
        while self.jobs is not None and not self.jobs.empty():
            device, job = self.jobs.get_nowait()
            link = self.link
            if link.client is None:
                job(None)
                continue
            spec = next(d.spec for d in self.devices if d.spec.name == device)
            self.polling = spec.name  # --hex's label
            link.client.timeout, link.client.retries = limits(spec, self.spec)
            link.stats = None  # a job is no poll: the device's and link's counts stay its polls'
            job(functools.partial(link.execute, spec.unit))

    def _sleep(self, seconds: float) -> None:
        """Until the next poll, the run's stop, or (with jobs) a job handed in."""
        if self.jobs is None:
            self.clock.wait(self.stop, seconds)
        else:  # in short slices, so that the run's stop is seen as soon as without jobs
            self.clock.wait(self.poke, min(seconds, 0.2))
            self.poke.clear()

    def limits(self) -> list[tuple[float, int]]:
        """The timeout and retries of each of its devices' transactions."""
        return [limits(d.spec, self.spec) for d in self.devices]

    def finished(self) -> bool:
        """--once, --rounds: every device has had its polls, or will be tried no more."""
        return bool(self.rounds) and not self._waiting()

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
                last = max(
                    (d.due if d.state == OFFLINE else d.due + (self.rounds - d.polls - 1) * d.spec.interval
                     for d in others),
                    default=-math.inf,
                )  # fmt: skip
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

    def _work(self) -> None:
        # What every poll asks of the settings, read once: each device's timeout and retries,
        # and --reconnect-each and --pause, which decide what follows a poll.
        for device in self.devices:
            device.limits = limits(device.spec, self.spec)
        self.reconnect_each, self.pause = self.spec.connection.reconnect_each, self.spec.connection.pause
        while not self.stop.is_set():
            self._run_jobs()
            waiting = self._waiting()
            if self.rounds and not waiting:  # finished
                return
            now = self.clock.monotonic()
            device = min(waiting, key=_DUE)  # the one that has waited longest
            ready_at = self.link.ready_at if self.link.client is None else -math.inf
            if device.due > now or ready_at > now:
                if self.idle is not None:
                    self.idle()
                self._sleep(max(0.0, max(device.due, ready_at) - now))
                continue
            if self.link.client is None:
                if not self._open([d for d in waiting if d.due <= now]):
                    continue
                if device.spec.grid and not device.polls:
                    # The grid starts with the first link open: opening sim:// (its imports) or
                    # a slow handshake is not a poll overrunning its slot.  What the first link
                    # made stays as long as the run: the collector need not walk it again.
                    gc.freeze()
                    device.due = self.clock.monotonic()
            self._poll(device)

    def _open(self, due: list[DeviceState]) -> bool:
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
            for device in due:  # its devices cannot be reached: offline meanwhile
                # Each poll's request could not go: a transaction with no connection, counted
                # as ping and read --interval count it.
                DeviceAndLink(device.stats, self.stats).transaction(error, 0)
                settled.extend(self._settle(device, None, error, when, not_before=self.link.ready_at))
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
        return True

    def view(self) -> LinkView:
        """The link as it is now, for a record: its own copy of the counts."""
        return LinkView(self.spec.name, self.state, self.open_failures, copy_stats(self.stats))

    def _label(self) -> str:
        return f"{self.spec.name} {self.polling}".rstrip()

    def _request_sent(self) -> None:
        """Run by the client right after a poll's first request has left: that is the poll's
        time."""
        self.stamp = self.clock.time()
        if self.sent is not None:
            self.sent()

    def _poll(self, device: DeviceState) -> None:
        link = self.link
        client = link.client
        assert client is not None  # a device is polled on an open link
        self.polling = device.spec.name
        self.stamp = None
        client.while_waiting = self._request_sent
        client.timeout, client.retries = device.limits  # one transaction at a time on a link
        link.stats = device.counted
        stats = self.stats
        untimed = stats.untimed
        readings: list[Reading] | None = None
        error: BaseException | None = None
        latency: float | None = None
        try:
            readings = device.spec.reader.read(device.execute)
            if stats.untimed == untimed:  # every reply of the poll timed
                latency = client.replied_at - client.work_sent_at
        except PartialRead as partial:
            readings, error = partial.readings, partial
        except FATAL:
            raise
        except (*KNOWN_ERRORS, OSError) as failure:
            error = link_failure(failure)  # a lost link the managed link closed: a new one next poll
        finally:
            client.while_waiting = None
        if client.deviations:  # --lenient took a reply as it was: the summary says so
            self.accepted.update(client.deviations)
        when = self.stamp
        if when is None:  # the request never left
            when = self.clock.time()
        for item in self._settle(device, readings, error, when, latency=latency):
            self.report(item)
        if self.reconnect_each and link.client is not None:
            # --reconnect-each: a new link every poll, for devices and gateways that serve one
            # client or leak connections; no wait, as nothing failed.
            link.drop(on_purpose=True)
        if self.idle is not None and (link.client is None or self.pause):
            self.idle()  # a new link or a pause comes before the next request

    def _settle(
        self, device, readings, error, when: float, not_before: float | None = None, latency=None
    ) -> list[Poll | Event]:
        """A poll's outcome in the device's state: the Poll, and the Event of its change of
        state if it had one, to report.  ``not_before``: its link cannot be opened, so the
        device is offline now and not tried before the link is."""
        now = self.clock.monotonic()
        device.polls += 1
        ok = readings is not None  # a partial read answered: the device is there
        if self.published:  # the outputs of a plant show them; a lone device's run counts its own
            device.stats.poll(ok)
        if ok:
            event = device.succeeded(now, when)
        else:
            event = device.failed(now, when, str(error), at_once=not_before is not None)
            if device.state == OFFLINE:
                device.due = max(device.due, not_before or 0.0)
        # Whether it will be tried again matters to an event's announcement, and decides an
        # offline device's next try; a device that answered is polled again while the run lasts.
        again = self._tried_again(device) if event is not None or device.state == OFFLINE else True
        if not again and event is not None and event.retry_in is not None:
            event = replace(event, retry_in=None)  # the run ends first: no next try to announce
        if self.published:
            poll = Poll(
                device.spec,
                when,
                readings,
                error,
                device.state,
                device.last_success,
                device.stats.copy(),
                self.view(),
                latency,
            )
        else:  # read on this thread, before the next poll: nothing to copy
            poll = Poll(
                device.spec, when, readings, error, device.state, device.last_success, None, None, latency
            )
        device.last_poll = poll
        return [poll] if event is None else [poll, event]


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
        self.stop = threading.Event()
        self.go = threading.Event()
        self.ended = False  # its duration ran out
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
        for started, worker in enumerate(self.workers):
            worker.deadline = deadline
            try:
                worker.thread.start()
            except RuntimeError as error:  # "can't start new thread": the system's limits
                # Said before any link is opened: those started wait for ``go``, and end.
                self.stop.set()
                self.go.set()
                for each in self.workers[:started]:
                    each.thread.join()
                raise ConnectionFailed(
                    f"cannot start a worker for each link: {started} of {len(self.workers)} links "
                    f"started before the system refused a thread ({error}); poll fewer links a "
                    "process, or raise its limits (ulimit -v, -u)"
                ) from None
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

    def _publish(self, wait: float | None = None) -> None:
        """Hand every record the workers have published to ``report``, on this thread; with
        ``wait``, wait that long for the first one (None: take only those already there)."""
        try:
            item = self.records.get(timeout=wait) if wait is not None else self.records.get_nowait()
        except queue.Empty:
            return
        while True:
            self.report(item)
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
