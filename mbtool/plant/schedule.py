"""The plant poller: every device of several links, one transaction at a time on each link,
every link at once.

A link (a serial bus, or a gateway or TCP device that takes one request at a time) has a
worker thread of its own.  It opens the link, and polls its devices as they fall due: when
several are due, the one that has waited longest goes first.  A poll reads every point of
the device (``MapReader``); the client keeps the line's silences and ``pause``.

A device that fails ``offline_after`` polls in a row (no response, a bad frame, an exception
to every read) is offline: it is tried again after a back-off that doubles from twice its
interval up to ``max_backoff``, so a dead meter costs one timeout a back-off, not one a poll
of the others.  One good poll brings it back online.  A link that cannot be opened (a
missing port, a refused connection) backs off the same way, and its devices are offline
meanwhile.  Each change of state is an ``Event``; each poll a ``Poll``; both go to
``report`` as they happen, from the link's thread.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from contextlib import ExitStack

from mbtool.codec.record import field, record
from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, PartialRead, link_failure
from mbtool.link.connection import Connection, close_quietly, open_client
from mbtool.link.stats import Counted
from mbtool.link.transport import ConnectionClosed
from mbtool.plant.stats import PollStats
from mbtool.registermap.plan import MapReader, Reading

ONLINE, OFFLINE, UNKNOWN = "online", "offline", "unknown"


@record
class DeviceSpec:
    """A device of the inventory: where it is, what to read, how often."""

    name: str
    link: str
    unit: int
    reader: MapReader = field(compare=False)
    tags: dict = field(default=None, compare=False)
    interval: float = 10.0
    offline_after: int = 3
    max_backoff: float = 300.0


@record
class LinkSpec:
    """A link of the inventory: a Connection whose unit each device gives."""

    name: str
    connection: Connection


@record
class Poll:
    """One device poll: its readings (all, or some with PartialRead as ``error``), or the
    error that kept it from reading any."""

    device: DeviceSpec
    time: float  # time.time(): when its first request went out, or when it failed
    readings: list[Reading] | None
    error: BaseException | None
    state: str  # the device's state after the poll


@record
class Event:
    """A change of state: a device going offline or coming back, a link that cannot be opened."""

    time: float
    kind: str  # "device" or "link"
    name: str
    state: str
    reason: str = ""
    retry_in: float | None = None  # seconds to the next try, when it is backed off


class DeviceState:
    """What the scheduler knows of a device: when it is due, and how it has fared."""

    def __init__(self, spec: DeviceSpec, now: float) -> None:
        self.spec = spec
        self.due = now
        self.state = UNKNOWN
        self.failures = 0  # failed polls in a row
        self.backoff = 0.0
        self.polls = 0
        self.last_success: float | None = None  # time.time()
        self.last_poll: Poll | None = None
        self.stats = PollStats()

    def succeeded(self, now: float, when: float) -> Event | None:
        was = self.state
        self.state, self.failures, self.backoff = ONLINE, 0, 0.0
        self.last_success = when
        self._next(now)
        return Event(when, "device", self.spec.name, ONLINE) if was == OFFLINE else None

    def failed(self, now: float, when: float, reason: str, at_once: bool = False) -> Event | None:
        """A failed poll; ``at_once``: offline now (its link cannot be opened)."""
        self.failures += 1
        if self.state == OFFLINE:
            self.backoff = min(2 * self.backoff, self.spec.max_backoff)
            self.due = now + self.backoff
            return None
        if self.failures < self.spec.offline_after and not at_once:
            self._next(now)
            return None
        self.state = OFFLINE
        self.backoff = min(2 * self.spec.interval, self.spec.max_backoff)
        self.due = now + self.backoff
        return Event(when, "device", self.spec.name, OFFLINE, reason, self.backoff)

    def _next(self, now: float) -> None:
        """The next slot of its interval; one that has passed already is skipped, not made up."""
        self.due += self.spec.interval
        if self.due < now:
            self.due = now


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
    ) -> None:
        self.spec = spec
        self.devices = devices
        self.report = report
        self.stop = stop
        self.rounds = rounds  # 0: until stopped
        self.trace = trace  # --hex: the client's trace, made from its framer
        self.link = ExitStack()
        self.client = None
        self.open_at = 0.0  # monotonic: not before this may the link be opened again
        self.backoff = 0.0
        self.state = UNKNOWN
        self.open_failures = 0  # times the link could not be opened
        self.crashed: BaseException | None = None
        self.thread = threading.Thread(target=self.run, name=f"link {spec.name}", daemon=True)

    def finished(self) -> bool:
        """--once, --rounds: every device has had its polls, or is offline after one at least."""
        if not self.rounds:
            return False
        return all(d.polls >= self.rounds or (d.state == OFFLINE and d.polls) for d in self.devices)

    def run(self) -> None:
        try:
            self._work()
        except BaseException as error:  # a bug: the plant stops, and says so on the main thread
            self.crashed = error
            self.stop.set()
        finally:
            close_quietly(self.link)

    def _work(self) -> None:
        while not self.stop.is_set() and not self.finished():
            now = time.monotonic()
            waiting = [d for d in self.devices if not (self.rounds and d.polls >= self.rounds)]
            due = [d for d in waiting if d.due <= now and self.open_at <= now]
            if not due:
                wake = max(min(d.due for d in waiting), self.open_at)
                self.stop.wait(max(0.0, wake - now))
                continue
            device = min(due, key=lambda d: d.due)  # the one that has waited longest
            if self.client is None and not self._open(due):
                continue
            self._poll(device)

    def _open(self, due: list[DeviceState]) -> bool:
        try:
            self.link = ExitStack()
            self.client = self.link.enter_context(open_client(self.spec.connection, trace=self.trace))
        except (*KNOWN_ERRORS, OSError) as error:
            error = link_failure(error)  # its devices' polls fail with it: exit 6, not 1
            self.client = None
            close_quietly(self.link)
            reason = str(error)
            now, when = time.monotonic(), time.time()
            first = self.state != OFFLINE
            longest = max(d.spec.max_backoff for d in self.devices)
            shortest = min(d.spec.interval for d in self.devices)
            self.backoff = min(2 * shortest if first else 2 * self.backoff, longest)
            self.open_at = now + self.backoff
            self.state = OFFLINE
            self.open_failures += 1
            if first:
                self.report(Event(when, "link", self.spec.name, OFFLINE, reason, self.backoff))
            for device in due:  # its devices cannot be reached: offline meanwhile
                # Each poll's request could not go: a transaction with no connection, counted
                # as ping and read --interval count it.
                device.stats.transaction(error, 0)
                self._end(device, None, error, when, at_once=True)
                device.due = max(device.due, self.open_at)
            return False
        if self.state == OFFLINE:
            self.report(Event(time.time(), "link", self.spec.name, ONLINE))
        self.state, self.backoff = ONLINE, 0.0
        return True

    def _poll(self, device: DeviceState) -> None:
        client, spec = self.client, device.spec
        stamp: list[float] = []
        client.while_waiting = lambda: stamp.append(time.time())  # the poll's time: its request out
        counted = Counted(client, device.stats)

        def execute(request):
            return counted(spec.unit, request)

        readings, error = None, None
        try:
            readings = spec.reader.read(execute)
        except PartialRead as partial:
            readings, error = partial.readings, partial
        except (*KNOWN_ERRORS, OSError) as failure:
            error = link_failure(failure)
            if isinstance(failure, OSError | ConnectionFailed | ConnectionClosed):
                close_quietly(self.link)  # the link is gone: open it anew for the next poll
                self.client = None
        finally:
            client.while_waiting = None
        self._end(device, readings, error, stamp[0] if stamp else time.time())

    def _end(self, device, readings, error, when: float, at_once: bool = False) -> None:
        now = time.monotonic()
        device.polls += 1
        ok = readings is not None  # a partial read answered: the device is there
        device.stats.poll(ok)
        if ok:
            event = device.succeeded(now, when)
        else:
            event = device.failed(now, when, str(error), at_once)
        poll = Poll(device.spec, when, readings, error, device.state)
        device.last_poll = poll
        self.report(poll)
        if event is not None:
            self.report(event)


class Plant:
    """Every link's worker, started together; ``run`` returns when they are done or stopped."""

    def __init__(
        self,
        links: dict[str, LinkSpec],
        devices: list[DeviceSpec],
        report: Callable[[Poll | Event], None],
        rounds: int = 0,
        trace=None,
    ) -> None:
        self.stop = threading.Event()
        now = time.monotonic()
        self.devices = {spec.name: DeviceState(spec, now) for spec in devices}
        self.workers = [
            LinkWorker(
                spec,
                [state for state in self.devices.values() if state.spec.link == name],
                report,
                self.stop,
                rounds,
                trace,
            )
            for name, spec in links.items()
        ]
        self.workers = [worker for worker in self.workers if worker.devices]

    def run(self, duration: float | None = None) -> None:
        for worker in self.workers:
            worker.thread.start()
        deadline = None if duration is None else time.monotonic() + duration
        try:
            for worker in self.workers:
                while worker.thread.is_alive():
                    left = None if deadline is None else deadline - time.monotonic()
                    if left is not None and left <= 0:
                        self.stop.set()
                        left = None
                    # Short joins: Ctrl-C reaches the main thread between them.
                    worker.thread.join(0.2 if left is None else min(0.2, left))
        finally:
            self.stop.set()
            for worker in self.workers:
                # A worker ends its transaction first: at most the link's timeout and retries.
                connection = worker.spec.connection
                worker.thread.join(connection.timeout * (connection.retries + 1) + 1)
        for worker in self.workers:
            if worker.crashed is not None:
                raise worker.crashed
