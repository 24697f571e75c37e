"""A plant device's state in mbtool poll's scheduler (mbtool.plant.schedule), in-process: offline
after failures in a row, backed off doubling, back online; its slots kept and those missed skipped
(issue 31)."""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import pytest

import mbtool.link
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link.connection import Connection
from mbtool.plant.stats import PollStats
from mbtool.plant.schedule import (
    OFFLINE,
    ONLINE,
    DeviceSpec,
    DeviceState,
    Event,
    LinkSpec,
    LinkWorker,
    Plant,
    Poll,
    Stop,
    view_of,
    views,
)


def _never_read(execute):
    raise AssertionError("the link was never opened: nothing is read")


# The reader of a device whose link is never opened: its polls fail before they read.
NEVER_READ = SimpleNamespace(blocks=(), read=_never_read, request=None)


def _state(interval=1.0, offline_after=3, max_backoff=10.0) -> DeviceState:
    spec = DeviceSpec("m", "bus", 1, None, {}, interval, offline_after, max_backoff)
    return DeviceState(spec, 0.0)


def test_a_device_goes_offline_after_failures_in_a_row_and_is_backed_off_doubling():
    state = _state()
    assert state.failed(0.0, 0.0, "silence") is None and state.due == 1.0
    assert state.succeeded(1.0, 1.0) is None and state.failures == 0  # not in a row
    assert state.failed(2.0, 2.0, "silence") is None
    assert state.failed(3.0, 3.0, "silence") is None
    event = state.failed(4.0, 4.0, "silence")
    assert (event.state, event.reason, event.retry_in) == (OFFLINE, "silence", 2.0)
    assert state.state == OFFLINE and state.due == 6.0
    waits = []
    for now in (6.0, 10.0, 18.0, 28.0):
        assert state.failed(now, now, "silence") is None  # one event for the change, not a probe
        waits.append(state.due - now)
    assert waits == [4.0, 8.0, 10.0, 10.0]  # doubling, up to max_backoff
    event = state.succeeded(38.0, 38.0)
    assert event.state == ONLINE and state.state == ONLINE and state.due == 39.0


def test_a_device_keeps_its_schedule_and_skips_slots_it_missed():
    state = _state(interval=2.0)
    state.succeeded(0.1, 0.1)
    assert state.due == 2.0  # its slot, not 2 s after this poll
    state.succeeded(7.5, 7.5)  # slots 4.0 and 6.0 passed while the link was busy
    assert state.due == 7.5


def _worker(rounds: int, *states: DeviceState, deadline: float | None = None) -> LinkWorker:
    worker = LinkWorker(LinkSpec("bus", None), list(states), lambda item: None, Stop(), rounds)
    worker.deadline = deadline
    return worker


def test_with_rounds_an_offline_device_is_tried_again_only_within_the_others_rounds():
    """--rounds 4: the device that answers has polls due at 1, 2 and 3 (its last); an offline
    one whose next try is at 2 is awaited, one whose next try is at 5 is done (issue 39.8)."""
    live, dead = _state(), _state()
    live.polls, live.due = 1, 1.0
    dead.polls, dead.state, dead.due = 1, OFFLINE, 2.0
    worker = _worker(4, live, dead)
    assert worker._tried_again(dead) and not worker.finished()
    dead.due = 5.0
    assert not worker._tried_again(dead) and dead.due == math.inf
    live.polls = 4
    assert worker.finished()


def test_a_try_after_the_deadline_is_not_promised():
    state = _state()
    state.due = 5.0
    assert not _worker(0, state, deadline=4.0)._tried_again(state)
    assert _worker(0, state, deadline=6.0)._tried_again(state) and _worker(0, state)._tried_again(state)


def test_records_reach_report_on_the_thread_that_runs_the_plant(monkeypatch):
    """Data flows one way (issue 41.5): the link threads publish their Poll and Event records,
    and only the thread that runs the plant hands them to ``report`` -- the output, the live
    view and the exporter's text never run on a link's thread."""

    def refused(framer_name):
        raise ConnectionFailed("cannot open fake://: not there")

    monkeypatch.setitem(mbtool.link.IN_PROCESS, "fake", refused)
    seen = []
    device = DeviceSpec("m", "bus", 1, NEVER_READ, {}, 0.01, 3, 0.02)
    plant = Plant(
        {"bus": LinkSpec("bus", Connection(port="fake://", timeout=0.05))},
        [device],
        lambda item: seen.append((type(item), threading.current_thread())),
        rounds=1,
    )
    plant.run()
    assert [kind for kind, _ in seen] == [Event, Poll, Event]  # link offline, its poll, device offline
    assert {thread for _, thread in seen} == {threading.current_thread()}


def test_a_poll_carries_copies_of_its_device_and_link_that_later_polls_do_not_change():
    """Readers see records (issue 41.5): a Poll holds the device's state, last success and
    counts and its link's as they were, so the output, the live view and the exporter never
    read what a link's thread is changing."""
    state = _state()
    worker = _worker(0, state)
    records: list = []
    worker._settle(records.append, state, state.groups[0], [], None, 5.0, 5.0)
    (poll,) = records
    assert (poll.state, poll.last_success, poll.stats.polls, poll.link.name) == (ONLINE, 5.0, 1, "bus")
    worker._settle(records.append, state, state.groups[0], None, NoResponse("silence"), 6.0, 6.0)
    assert state.stats.polls == 2 and state.stats.failed_polls == 1
    assert poll.stats.polls == 1 and poll.stats.failed_polls == 0  # its own copy
    view = view_of(poll)
    assert (view.spec, view.state, view.last_success, view.last_poll) == (state.spec, ONLINE, 5.0, poll)
    assert [v.state for v in views([state.spec]).values()] == ["unknown"]  # before any poll


def test_a_copy_of_a_devices_counts_is_its_own_whole_and_later_transactions_are_not_in_it():
    stats = PollStats()
    stats.poll(True)
    stats.answered(2, 0.004)  # on its retry
    stats.transaction(NoResponse("silence"), 1)
    copy = stats.copy()
    stats.poll(False)
    stats.answered(1, 0.3)
    assert type(copy) is PollStats
    assert (copy.polls, copy.failed_polls, copy.transactions, copy.recovered) == (1, 0, 2, 1)
    assert (copy.outcomes["answered"], copy.outcomes["timeout"], copy.rtt.count) == (1, 1, 1)
    assert (stats.polls, stats.transactions, stats.rtt.count) == (2, 3, 2)


def _two_links(monkeypatch) -> Plant:
    """A plant of two links, a and b, each with one device that cannot be reached."""

    def refused(framer_name):
        raise ConnectionFailed("cannot open fake://: not there")

    monkeypatch.setitem(mbtool.link.IN_PROCESS, "fake", refused)
    links = {name: LinkSpec(name, Connection(port="fake://", timeout=0.05)) for name in ("a", "b")}
    devices = [DeviceSpec(f"m{name}", name, 1, NEVER_READ, {}, 0.01, 3, 0.02) for name in links]
    return Plant(links, devices, lambda item: None, rounds=1)


def _run_within(plant: Plant, seconds: float) -> BaseException | None:
    """What ``plant.run()`` raised (None if nothing), failing the test if it has not returned
    within ``seconds``: a hang is the defect these tests look for."""
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            plant.run()
            outcome.append(None)
        except BaseException as error:
            outcome.append(error)

    runner = threading.Thread(target=run, name="runs the plant", daemon=True)
    runner.start()
    runner.join(seconds)
    assert outcome, f"Plant.run did not return within {seconds} s"
    return outcome[0]


def test_a_worker_whose_thread_cannot_be_started_ends_the_run_with_one_line(monkeypatch):
    """Issue 44: a capped address space fails a thread's start with MemoryError, not only the
    RuntimeError of "can't start new thread"; the run says so in one line (exit 6), not exit 1."""
    plant = _two_links(monkeypatch)
    start = threading.Thread.start

    def refuses_b(thread):
        if thread.name == "link b":
            raise MemoryError
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", refuses_b)
    error = _run_within(plant, 10)
    assert isinstance(error, ConnectionFailed), repr(error)
    assert str(error).startswith("cannot start a worker for each link: 1 of 2 links started"), error


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the thread's death
def test_a_worker_whose_thread_dies_in_its_start_up_ends_the_run_not_hangs_it(monkeypatch):
    """Issue 44: a thread that dies in its own start-up (MemoryError under a capped address
    space, before it says it began) leaves Thread.start waiting for ever; the run gives the
    workers a deadline to start, and ends with one line (exit 6)."""
    plant = _two_links(monkeypatch)
    plant.start_within = 0.5
    bootstrap = threading.Thread._bootstrap_inner

    def dies_in_start_up(thread):
        if thread.name == "link b":
            raise MemoryError  # before the thread says it began, as CPython's own start-up can
        bootstrap(thread)

    monkeypatch.setattr(threading.Thread, "_bootstrap_inner", dies_in_start_up)
    error = _run_within(plant, 10)
    assert isinstance(error, ConnectionFailed), repr(error)
    assert str(error).startswith("cannot start a worker for each link: 1 of 2 links started"), error
    assert "did not start within 0.5 s" in str(error)


def test_the_watchdog_sees_a_worker_stuck_in_its_work_or_records_stuck_before_the_output(monkeypatch):
    """Issue 44: Plant.moved, which systemd's watchdog asks each period, says no when a link's
    worker neither turned its loop nor waited on schedule at two asks running, or when records
    waited at both and none was handed on; a worker waiting for its next poll is moving."""
    plant = _two_links(monkeypatch)
    a, b = plant.workers
    for worker in plant.workers:
        worker.thread = SimpleNamespace(is_alive=lambda: True)
    assert plant.moved()  # the first ask: nothing to compare with
    a.turns += 1
    b.asleep = True
    assert plant.moved()  # a polled, b waits for its next poll
    a.turns += 1
    b.asleep = False  # b woke for its poll: under way, not stuck
    assert plant.moved()
    a.turns += 1
    assert not plant.moved()  # b in the same poll since the last ask: stuck in its work
    a.turns += 1
    b.turns += 1
    plant.records.put("a record")
    assert plant.moved()  # a record waits, but none waited at the last ask
    a.turns += 1
    b.asleep = True
    assert not plant.moved()  # it waits still, and nothing was handed on: the output is stuck
    plant._publish()
    a.turns += 1
    assert plant.moved()
