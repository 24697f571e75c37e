"""The plant's engine (mbtool.plant.schedule.LinkWorker on a managed link) sans-IO, on a fake
clock: slots, who goes first, offline and back-off, a link that cannot be opened or is lost,
rounds and a run's end (issue 41, points 1 and 8); the jobs poll --mqtt hands a link (issue 42).

The worker runs on the test's own thread with a fake clock (its waits move the clock, they do
not sleep) and a fake link (each device's transactions scripted), so every test takes
milliseconds and says exactly when each poll was made."""

from __future__ import annotations

import math
import os
import sys
from contextlib import contextmanager
from types import SimpleNamespace

import pytest

from mbtool.codec.errors import ModbusException, RequestError
from mbtool.errors import ConnectionFailed, NoResponse, PartialRead
from mbtool.link.connection import Connection
from mbtool.link.managed import Backoff
from mbtool.link.transport import ConnectionClosed
from mbtool.plant.schedule import (
    OFFLINE,
    ONLINE,
    OVERRUN,
    DeviceSpec,
    DeviceState,
    Event,
    Group,
    LinkSpec,
    LinkWorker,
    Poll,
    Stop,
    view_of,
)
from mbtool.registermap.groups import ONCE

EPOCH = 1_700_000_000.0


class Clock:
    """The scheduler's clocks, moved only by its waits (and by a transaction that takes time)."""

    def __init__(self, stop_at: float | None = None) -> None:
        self.now = 0.0
        self.stop_at = stop_at  # the run's end: the wait that reaches it stops the worker
        self.waits = 0

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return EPOCH + self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds

    def wait(self, stop: Stop, seconds: float) -> None:
        self.waits += 1
        assert self.waits < 10_000, "the worker never ends"
        self.now += seconds
        if self.stop_at is not None and self.now >= self.stop_at:
            stop.set()


class Reader:
    """A device's map, as the worker uses it: one request a poll."""

    points = ()
    blocks = ("read",)
    request = None

    def read(self, execute):
        return [execute("read")]


class Client:
    """The fake link's client: each unit's transactions as the test scripts them ("reply",
    "silent", "lost", "exception", "partial", "slow N": a reply N seconds after its request,
    "unfit": a request the link cannot carry), then replies."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.while_waiting = None
        self.timeout, self.retries = 1.0, 0
        self.attempts, self.rtt, self.ended_at = 0, None, float("-inf")
        self.deviations: dict[str, None] = {}  # --lenient's, each kind once
        self.work_sent_at = self.replied_at = 0.0

    def execute(self, unit: int, request):
        link = self.link
        link.asked.append((unit, link.clock.now, self.timeout, self.retries))
        work = self.while_waiting
        if work is not None:  # as the real client: run once, after the poll's first request
            self.while_waiting = None
            work()
        self.attempts, self.rtt = 1, None
        steps = link.script.get(unit, [])
        step = steps.pop(0) if steps else "reply"
        if step == "silent":
            raise NoResponse(f"no response from unit {unit}")
        if step == "lost":
            raise ConnectionClosed("the device closed the connection")
        if step == "exception":
            raise ModbusException(3, 2)
        if step == "unfit":
            raise RequestError("a read to the broadcast unit gets no reply")
        if step.startswith("slow "):
            link.clock.now += float(step.split()[1])
        self.rtt = 0.01
        if step == "partial":
            raise PartialRead(["a value", "a refusal"], [ModbusException(3, 2)])
        return f"reply from {unit}"


class Link:
    """``open_link`` for the worker: each open takes the next of ``opens`` ("ok", "refused")."""

    def __init__(self, clock: Clock, script: dict, opens: list[str]) -> None:
        self.clock = clock
        self.script = {unit: list(steps) for unit, steps in script.items()}
        self.opens = list(opens)
        self.opened: list[float] = []
        self.asked: list[tuple] = []

    @contextmanager
    def __call__(self):
        self.opened.append(self.clock.now)
        if (self.opens.pop(0) if self.opens else "ok") == "refused":
            raise ConnectionRefusedError(111, "Connection refused")
        yield Client(self)


def device(name: str, unit: int, interval=1.0, offline_after=3, max_backoff=10.0, **options) -> DeviceSpec:
    return DeviceSpec(name, "bus", unit, Reader(), {}, interval, offline_after, max_backoff, **options)


def run(devices, script=None, opens=(), rounds=0, until=None, due=None, link_options=None, **options):
    """One link's worker to its end: the records it published, its link, the worker.
    ``link_options``: the link's Connection's; ``options``: the worker's."""
    clock = Clock(until)
    states = [DeviceState(spec, clock.now) for spec in devices]
    for state in states:
        state.due = (due or {}).get(state.spec.name, state.due)
    records: list[Poll | Event] = []
    link = Link(clock, script or {}, list(opens))
    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1, **(link_options or {})))
    worker = LinkWorker(spec, states, records.append, Stop(), rounds, clock=clock, open_link=link, **options)
    worker.deadline = None if until is None else until
    worker.run()
    if worker.crashed is not None:
        raise worker.crashed
    return records, link, worker


def polls(records, name=None) -> list[tuple[str, float]]:
    return [
        (r.device.name, r.time - EPOCH)
        for r in records
        if isinstance(r, Poll) and name in (None, r.device.name)
    ]


def events(records) -> list[tuple]:
    return [(r.kind, r.name, r.state, r.time - EPOCH, r.retry_in) for r in records if isinstance(r, Event)]


def test_each_device_keeps_its_own_interval_on_one_link():
    records, link, _ = run([device("a", 1, interval=1.0), device("b", 2, interval=2.0)], rounds=3)
    assert polls(records) == [("a", 0), ("b", 0), ("a", 1), ("a", 2), ("b", 2), ("b", 4)]
    assert link.opened == [0.0]  # one link, kept


def test_of_the_devices_due_the_one_that_has_waited_longest_goes_first():
    records, _, _ = run([device("a", 1), device("b", 2)], rounds=1, due={"a": 0.0, "b": -0.5})
    assert [name for name, _ in polls(records)] == ["b", "a"]


def test_a_slot_missed_is_skipped_not_made_up():
    state = DeviceState(device("a", 1, interval=2.0), 0.0)
    state.succeeded(0.1, 0.1)
    assert state.due == 2.0
    state.succeeded(7.5, 7.5)
    assert state.due == 7.5


def test_a_device_goes_offline_after_failures_in_a_row_and_is_tried_doubling_up_to_max_backoff():
    records, _, _ = run([device("dead", 9)], script={9: ["silent"] * 20}, until=30)
    assert [t for _, t in polls(records)] == [0, 1, 2, 4, 8, 16, 26]
    assert events(records) == [("device", "dead", OFFLINE, 2, 2.0)]  # one event for the change
    assert [r.state for r in records if isinstance(r, Poll)][:3] == ["unknown", "unknown", OFFLINE]


def test_one_good_poll_brings_an_offline_device_back():
    records, _, _ = run([device("m", 1)], script={1: ["silent"] * 3}, until=6)
    assert [t for _, t in polls(records)] == [0, 1, 2, 4, 5]
    assert events(records) == [("device", "m", OFFLINE, 2, 2.0), ("device", "m", ONLINE, 4, None)]


def test_an_exception_to_every_read_is_a_failed_poll_but_a_partial_read_is_an_answer():
    records, _, _ = run([device("m", 1, offline_after=1)], script={1: ["exception"]}, rounds=1)
    assert events(records) == [("device", "m", OFFLINE, 0, None)]  # the run ends first: no next try
    records, _, _ = run([device("m", 1, offline_after=1)], script={1: ["partial"]}, rounds=1)
    (poll,) = [r for r in records if isinstance(r, Poll)]
    assert isinstance(poll.error, PartialRead) and poll.readings == ["a value", "a refusal"]
    assert poll.state == ONLINE and events(records) == []


def test_a_link_that_cannot_be_opened_backs_off_by_the_one_rule_and_its_devices_are_offline():
    records, link, worker = run([device("m", 1)], opens=["refused", "refused", "ok"], until=7)
    assert link.opened == [0, 2, 6]  # twice the interval, doubling: 2 s, then 4 s
    assert events(records) == [
        ("link", "bus", OFFLINE, 0, 2.0),  # once, when it went offline
        ("device", "m", OFFLINE, 0, 2.0),
        ("link", "bus", ONLINE, 6, None),
        ("device", "m", ONLINE, 6, None),
    ]
    failed = [r for r in records if isinstance(r, Poll) and r.readings is None]
    assert [type(r.error) for r in failed] == [ConnectionFailed, ConnectionFailed]  # exit 6, not 1
    assert worker.open_failures == 2 and worker.state == ONLINE


def test_a_lost_link_is_opened_again_no_sooner_than_its_first_back_off_after_it_was_opened():
    records, link, _ = run([device("m", 1, interval=0.5)], script={1: ["reply", "lost"]}, until=2)
    assert link.opened == [0, 1.0]  # lost at 0.5: the next open waits out 2 x 0.5 s from 0
    assert [t for _, t in polls(records)] == [0, 0.5, 1.0, 1.5]
    lost = [r for r in records if isinstance(r, Poll) and r.readings is None]
    assert [type(r.error) for r in lost] == [ConnectionClosed]


def test_a_link_that_served_a_while_is_opened_again_at_once_when_lost():
    records, link, _ = run([device("m", 1, interval=3.0)], script={1: ["reply", "lost"]}, until=7)
    assert link.opened == [0, 6]  # lost at 3, long after it opened: the next poll opens it


def test_with_rounds_an_offline_device_gets_fewer_and_the_run_does_not_wait_out_its_back_off():
    records, _, worker = run(
        [device("live", 1), device("dead", 2, offline_after=1)], script={2: ["silent"] * 9}, rounds=4
    )
    assert [t for _, t in polls(records, "live")] == [0, 1, 2, 3]
    assert [t for _, t in polls(records, "dead")] == [0, 2]  # its next try, at 6, is after live's last
    assert events(records) == [("device", "dead", OFFLINE, 0, 2.0)]
    assert worker.finished() and worker.clock.now == 3  # the run ended with live's last poll


def test_a_try_after_the_runs_end_is_not_announced():
    records, _, _ = run([device("m", 1, offline_after=1)], script={1: ["silent"] * 9}, until=1.5)
    assert events(records) == [("device", "m", OFFLINE, 0, None)]
    records, _, _ = run([device("m", 1, offline_after=1)], script={1: ["silent"] * 9}, until=2.5)
    assert events(records) == [("device", "m", OFFLINE, 0, 2.0)]


def test_each_device_has_its_own_timeout_and_retries_on_the_link():
    _, link, _ = run([device("slow", 1, timeout=0.8, retries=2), device("fast", 2)], rounds=1)
    assert [(unit, timeout, retries) for unit, _, timeout, retries in link.asked] == [
        (1, 0.8, 2),
        (2, 0.1, 0),
    ]


def test_every_transaction_is_counted_for_its_device_and_its_link():
    records, _, worker = run([device("a", 1), device("b", 2)], script={2: ["silent"]}, rounds=2)
    a, b = worker.devices
    assert (a.stats.transactions, a.stats.outcomes["answered"]) == (2, 2)
    assert (b.stats.outcomes["answered"], b.stats.outcomes["timeout"]) == (1, 1)
    assert worker.stats.transactions == 4 and worker.stats.outcomes["timeout"] == 1
    last = [r for r in records if isinstance(r, Poll)][-1]
    assert last.link.stats.transactions == 4  # the record carries the link's counts as they were


def test_each_poll_is_stamped_when_its_request_left():
    records, _, _ = run([device("a", 1, interval=2.0)], rounds=2)
    assert [r.time for r in records if isinstance(r, Poll)] == [EPOCH, EPOCH + 2.0]


@pytest.mark.parametrize("rounds", [1, 3])
def test_rounds_end_the_run_once_every_device_has_had_them(rounds):
    records, _, worker = run([device("a", 1), device("b", 2, interval=0.5)], rounds=rounds)
    assert len(polls(records, "a")) == len(polls(records, "b")) == rounds
    assert worker.finished()


def test_a_job_handed_in_runs_between_polls_on_the_workers_own_link_with_its_devices_limits():
    """poll --mqtt's writes (LinkWorker.submit): run by the link's thread before its next poll,
    through its ManagedLink -- the link is opened once, never a second time for a job -- with
    the job's device's timeout and retries, and not counted as a poll of it."""
    clock = Clock()
    states = [DeviceState(device("a", 1), 0.0), DeviceState(device("b", 2, timeout=0.8, retries=2), 0.0)]
    link = Link(clock, {}, [])
    ran = []

    def job(execute):
        ran.append(clock.now)
        execute("write")

    def report(record):
        if isinstance(record, Poll) and record.device.name == "a" and record.time == EPOCH:
            worker.submit("b", job)  # as the publisher's thread does, after a poll

    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1))
    worker = LinkWorker(spec, states, report, Stop(), 2, clock=clock, open_link=link)
    worker.accept_jobs()
    worker.run()
    assert worker.crashed is None
    assert link.opened == [0.0]
    # a's poll, the job (with b's limits) before b's poll, then the second round
    assert [(unit, t, timeout, retries) for unit, t, timeout, retries in link.asked] == [
        (1, 0.0, 0.1, 0),
        (2, 0.0, 0.8, 2),
        (2, 0.0, 0.8, 2),
        (1, 1.0, 0.1, 0),
        (2, 1.0, 0.8, 2),
    ]
    assert ran == [0.0]
    assert [s.stats.transactions for s in worker.devices] == [2, 2]  # the polls' alone


def test_a_job_while_the_link_is_lost_is_told_so_and_does_not_open_it_before_its_back_off():
    clock = Clock()
    states = [DeviceState(device("a", 1), 0.0)]
    link = Link(clock, {1: ["lost"]}, [])
    given = []

    def report(record):
        if isinstance(record, Poll) and record.readings is None:
            worker.submit("a", given.append)  # a write handed in while the link is down

    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1))
    worker = LinkWorker(spec, states, report, Stop(), 3, clock=clock, open_link=link)
    worker.accept_jobs()
    worker.run()
    assert worker.crashed is None
    assert given == [None]
    assert link.opened == [0.0, 2.0]  # the polls' opens, the second after the back-off: none for the job


# --- read --interval's one device on the engine (plant.polling) ---------------------------------


def test_on_a_grid_a_poll_that_overruns_its_slot_skips_the_slots_it_missed_and_counts_them():
    records, _, worker = run([device("m", 1, grid=True)], script={1: ["reply", "slow 2.5"]}, rounds=3)
    # The second poll ends 3.5 s in: slots 2 and 3 have passed, the third poll takes slot 4.
    assert [t for _, t in polls(records)] == [0, 1, 4]
    assert worker.devices[0].skipped == 2
    records, _, worker = run([device("m", 1)], script={1: ["reply", "slow 2.5"]}, rounds=3)
    assert [t for _, t in polls(records)] == [0, 1, 3.5]  # a plant's device: at once, no grid


def test_on_a_grid_the_last_poll_counts_no_slots_skipped_after_it():
    _, _, worker = run([device("m", 1, grid=True)], script={1: ["reply", "slow 5"]}, rounds=2)
    assert worker.devices[0].skipped == 0


def test_a_device_never_offline_keeps_its_polls_through_a_link_that_would_not_open():
    """read --interval --polls 2 whose first open is refused: two polls, not one and an end."""
    records, link, _ = run(
        [device("m", 1, offline_after=0, grid=True)], opens=["refused"], rounds=2, backoff=Backoff(0.1)
    )
    polled = [r for r in records if isinstance(r, Poll)]
    assert [(r.time - EPOCH, r.error is None) for r in polled] == [(0, False), (1, True)]
    assert link.opened == [0, 1]
    assert [r.state for r in polled] == ["unknown", ONLINE]  # never offline
    assert [e for e in events(records) if e[0] == "device"] == []


def test_reconnect_each_opens_a_new_link_for_every_poll_at_once():
    _, link, _ = run([device("m", 1)], rounds=3, link_options={"reconnect_each": True})
    assert link.opened == [0, 1, 2]


def test_a_request_the_link_cannot_carry_ends_the_run_rather_than_failing_a_poll():
    with pytest.raises(RequestError):
        run([device("m", 1)], script={1: ["unfit"]}, rounds=3)


def test_the_hooks_run_when_a_request_has_left_and_before_the_worker_waits():
    said = []
    records, _, _ = run(
        [device("m", 1)],
        rounds=2,
        sent=lambda: said.append("sent"),
        idle=lambda: said.append("idle"),
        published=False,
    )
    assert [type(r).__name__ for r in records] == ["Poll", "Poll"]
    assert said == ["sent", "idle", "sent"]


def test_an_unpublished_poll_that_changes_nothing_is_handed_over_as_its_time_and_readings():
    """read --interval's worker (unpublished, untimed) makes no Poll of a poll that answered a
    device online and read every point: its time and readings are all such a Poll would say.
    One that changes the device's state (the first), fails, or reads some points is a Poll."""
    answered: list = []
    records, _, _ = run(
        [device("m", 1, offline_after=0, grid=True)],
        script={1: ["reply", "reply", "silent", "partial", "reply"]},
        rounds=5,
        published=False,
        timed=False,
        answered=lambda when, readings: answered.append((when - EPOCH, readings)),
    )
    assert [(r.time - EPOCH, r.state, r.error.__class__.__name__) for r in records] == [
        (0, ONLINE, "NoneType"),
        (2, ONLINE, "NoResponse"),
        (3, ONLINE, "PartialRead"),
    ]
    assert answered == [(1, ["reply from 1"]), (4, ["reply from 1"])]


def test_unpublished_records_carry_no_copies_and_the_links_counts_are_the_devices():
    records, _, worker = run([device("m", 1)], script={1: ["silent"]}, rounds=2, published=False)
    assert all(r.stats is None and r.link is None for r in records)
    assert worker.stats.transactions == 2 and worker.stats.outcomes["timeout"] == 1


# --- poll groups: each its own clock on the one link (issue 44) -----------------------------


class Timed:
    """A group's reads on the fake clock: ``reads`` transactions of ``seconds`` each on the line,
    a reading a point named."""

    request = None

    def __init__(self, clock: Clock, names: tuple[str, ...], reads: int = 1, seconds: float = 0.0) -> None:
        self.clock, self.names, self.seconds = clock, names, seconds
        self.blocks = [f"read {n}" for n in range(reads)]
        self.points = [SimpleNamespace(name=name) for name in names]

    def read(self, execute):
        for request in self.blocks:
            execute(request)
            self.clock.now += self.seconds
        return [SimpleNamespace(point=point, value=self.clock.now, error=None) for point in self.points]


def grouped(clock: Clock, *groups: tuple, offline_after: int = 3) -> DeviceSpec:
    """A device of ``groups``: (name, interval, reads, seconds a read)."""
    made = tuple(
        Group(group, interval, Timed(clock, (f"{group}_point",), reads, seconds))
        for group, interval, reads, seconds in groups
    )
    return DeviceSpec("m", "bus", 1, None, {}, 10.0, offline_after, 60.0, groups=made)


def run_groups(clock: Clock, devices, script=None, rounds=0):
    """As ``run``; a link kept busy (it never waits) is stopped by its records' time."""
    records: list[Poll | Event] = []
    stop = Stop()

    def report(record):
        records.append(record)
        if clock.stop_at is not None and clock.now >= clock.stop_at:
            stop.set()

    link = Link(clock, script or {}, [])
    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1))
    states = [DeviceState(spec_, clock.now) for spec_ in devices]
    worker = LinkWorker(spec, states, report, stop, rounds, clock=clock, open_link=link)
    worker.run()
    if worker.crashed is not None:
        raise worker.crashed
    return records, link, worker


def group_polls(records, group: str) -> list[float]:
    return [round(r.time - EPOCH, 3) for r in records if isinstance(r, Poll) and r.group == group]


def test_of_the_groups_due_the_earliest_deadline_goes_first_and_each_keeps_its_own_clock():
    clock = Clock(stop_at=4.5)
    device_ = grouped(clock, ("slow", 3.0, 1, 0.1), ("fast", 1.0, 1, 0.1))  # slow first: no tie
    records, link, _ = run_groups(clock, [device_])
    # Both due at 0: the fast group's deadline (1 s) is before the slow one's (3 s).
    assert [r.group for r in records if isinstance(r, Poll)][:2] == ["fast", "slow"]
    assert group_polls(records, "fast") == [0, 1, 2, 3, 4]
    assert group_polls(records, "slow") == [0.1, 3.1]  # its slot, 3.0, came while fast read
    assert link.opened == [0.0]


def test_a_fast_group_is_never_held_up_by_more_than_one_transaction_of_a_slow_groups_long_read():
    """The slow group reads 8 requests of 0.3 s (2.4 s): its poll lets the fast group, whose
    deadline is earlier, go between two of its transactions."""
    clock = Clock(stop_at=12)
    device_ = grouped(clock, ("fast", 1.0, 1, 0.02), ("slow", 10.0, 8, 0.3))
    records, _, worker = run_groups(clock, [device_])
    fast = group_polls(records, "fast")
    assert len(fast) == 13  # the last during the slow group's second poll, at 10
    assert all(abs(t - n) <= 0.3 for n, t in enumerate(fast))  # at most one slow read late
    assert any(t - n > 0.1 for n, t in enumerate(fast))  # and held up by one
    assert group_polls(records, "slow") == [0.02, 10.02]  # after fast's, due with it at 10
    slow = [r for r in records if isinstance(r, Poll) and r.group == "slow"]
    assert [reading.point.name for reading in slow[0].readings] == ["slow_point"]
    assert worker.devices[0].stats.polls == 15  # 13 + 2: each group's poll is a poll of the device


def test_a_groups_poll_carries_its_own_points_and_the_latest_of_every_point():
    clock = Clock(stop_at=1.5)
    device_ = grouped(clock, ("fast", 1.0, 1, 0.0), ("slow", 10.0, 1, 0.0))
    records, _, _ = run_groups(clock, [device_])
    first, second, third = [r for r in records if isinstance(r, Poll)]
    assert [r.point.name for r in first.readings] == ["fast_point"]
    assert [r.point.name for r in second.readings] == ["slow_point"]
    assert sorted(r.point.name for r in third.latest) == ["fast_point", "slow_point"]
    view = view_of(third)  # what the Prometheus text and the live view show: every point's last
    assert sorted(r.point.name for r in view.last_poll.readings) == ["fast_point", "slow_point"]
    assert (third.pace.group, third.pace.asked, third.pace.achieved, third.pace.polls) == (
        "fast",
        1.0,
        1.0,
        2,
    )


def test_what_is_read_once_is_read_at_start_and_again_after_each_reconnect():
    clock = Clock(stop_at=7)
    device_ = grouped(clock, ("fast", 1.0, 1, 0.0), (ONCE, math.inf, 1, 0.0))
    records, link, _ = run_groups(clock, [device_], script={1: ["reply", "reply", "reply", "lost"]})
    assert link.opened == [0, 3]
    assert group_polls(records, ONCE) == [
        0,
        3,
    ]  # first at start (its deadline is now), then after the reconnect
    assert group_polls(records, "fast") == [0, 1, 2, 3, 4, 5, 6]


def test_rounds_poll_every_group_that_many_times_and_a_group_read_once_once():
    clock = Clock()
    device_ = grouped(clock, ("fast", 1.0, 1, 0.0), ("slow", 2.0, 1, 0.0), (ONCE, math.inf, 1, 0.0))
    records, _, worker = run_groups(clock, [device_], rounds=2)
    assert (
        len(group_polls(records, "fast")),
        len(group_polls(records, "slow")),
        len(group_polls(records, ONCE)),
    ) == (2, 2, 1)
    assert worker.finished() and clock.now == 2


def test_an_offline_devices_groups_all_wait_for_its_back_off():
    clock = Clock(stop_at=6)
    device_ = grouped(clock, ("fast", 1.0, 1, 0.0), ("slow", 2.0, 1, 0.0), offline_after=1)
    records, _, _ = run_groups(clock, [device_], script={1: ["silent"] * 3})
    # offline at its first poll: its back-off (twice its fastest group's interval) holds every group
    # (the slow group, due since 0, goes first at the back-off's end; failing, the back-off doubles)
    assert [(r.group, round(r.time - EPOCH, 3)) for r in records if isinstance(r, Poll)] == [
        ("fast", 0), ("slow", 2)
    ]  # fmt: skip
    assert events(records) == [("device", "m", OFFLINE, 0, 2.0)]


def test_a_link_that_cannot_keep_up_says_so_once_with_the_figures():
    """Two groups asking 4 + 2 reads a second of 0.25 s each: the line carries 4."""
    clock = Clock(stop_at=20)
    device_ = grouped(clock, ("fast", 0.5, 2, 0.25), ("slow", 1.0, 2, 0.25))
    records, _, worker = run_groups(clock, [device_])
    said = [r for r in records if isinstance(r, Event) and r.state == OVERRUN]
    assert [(e.kind, e.name, e.reason) for e in said] == [
        ("link", "bus", "asked 6.0 reads/s, the line carries 4.0")
    ]
    paces = {r.group: r.pace for r in records if isinstance(r, Poll)}
    assert paces["slow"].overruns > 0 and paces["slow"].achieved > 1.0


def test_a_link_that_keeps_up_says_nothing_of_its_pace():
    clock = Clock(stop_at=20)
    records, _, _ = run_groups(clock, [grouped(clock, ("fast", 1.0, 2, 0.25), ("slow", 5.0, 4, 0.25))])
    assert not [r for r in records if isinstance(r, Event)]
    assert all(r.pace.overruns == 0 for r in records if isinstance(r, Poll) and r.group == "fast")


def test_a_reconnect_after_a_device_has_had_its_rounds_reads_nothing_of_it_again():
    """Device m is done at 2 (three rounds of its fast group, its ONCE group read at start);
    device b loses the link at 3 and opens it again at 6: what m reads once stays read."""
    clock = Clock()
    m = grouped(clock, ("fast", 1.0, 1, 0.0), (ONCE, math.inf, 1, 0.0))
    b = DeviceSpec("b", "bus", 2, Reader(), {}, 3.0, 3, 60.0)
    records, link, _ = run_groups(clock, [m, b], script={2: ["reply", "lost"]}, rounds=3)
    assert link.opened == [0, 6]
    assert group_polls(records, ONCE) == [0]
    assert group_polls(records, "fast") == [0, 1, 2]
    assert [round(r.time - EPOCH, 3) for r in records if isinstance(r, Poll) and r.device.name == "b"] == [
        0,
        3,
        6,
    ]


def test_a_device_whose_every_point_is_read_once_waits_for_a_reconnect_rather_than_crashing():
    """Every group of it read once (a nameplate): no slot is left to wait for, and the worker
    waits for a reconnect (a minute at a time) until the run is stopped.  It asked the earliest
    of no devices due and crashed the plant (ValueError: min() arg is an empty sequence)."""
    clock = Clock(stop_at=150)
    records, link, worker = run_groups(clock, [grouped(clock, (ONCE, math.inf, 1, 0.0))])
    assert group_polls(records, ONCE) == [0]
    assert link.opened == [0] and clock.now >= 150
    assert worker.crashed is None


def test_a_read_that_would_make_a_faster_group_late_waits_for_it_on_a_serial_line():
    """The slow group falls due at 0.9 s and its read holds the line 0.3 s: read then, it would
    make the fast group, due at 1.0 s, late by 0.2 s.  It waits for the fast group instead."""
    clock = Clock(stop_at=3.5)
    device_ = grouped(clock, ("fast", 1.0, 1, 0.02), ("slow", 10.0, 1, 0.3))
    records, link = [], Link(clock, {}, [])
    state = DeviceState(device_, 0.0)
    fast, slow = state.groups
    slow.due, fast.line_time, slow.line_time = 0.9, 0.02, 0.3  # the line's time of each read
    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1))
    worker = LinkWorker(spec, [state], records.append, Stop(), 0, clock=clock, open_link=link)
    worker.run()
    assert group_polls(records, "fast") == [0, 1, 2, 3]
    assert group_polls(records, "slow") == [1.02]  # after the fast group's read, not at 0.9


def test_a_read_is_held_back_no_later_than_a_tenth_of_its_own_interval():
    """Fast groups that leave the line no gap long enough: the slow read goes once it is a tenth
    of its interval late, not never."""
    clock = Clock(stop_at=2.5)
    device_ = grouped(clock, ("fast", 0.1, 1, 0.05), ("slow", 2.0, 1, 0.3))
    state = DeviceState(device_, 0.0)
    fast, slow = state.groups
    fast.line_time, slow.line_time = 0.05, 0.3
    records, link = [], Link(clock, {}, [])
    spec = LinkSpec("bus", Connection(port="fake://", timeout=0.1))
    LinkWorker(spec, [state], records.append, Stop(), 0, clock=clock, open_link=link).run()
    (first, *_) = group_polls(records, "slow")
    assert 0.2 <= first <= 0.3  # held while less than 0.2 s late, then read


def _engine_bytecodes(rounds: int, grid: bool = False, **options) -> int:
    """The bytecodes the engine itself (plant/schedule.py) runs in ``rounds`` polls of a device
    on a link of its own that answers every poll (its other code, the link's and the client's,
    not counted)."""
    ran = [0]
    engine = os.path.join("plant", "schedule.py")

    def trace(frame, event, arg):
        if not frame.f_code.co_filename.endswith(engine):
            return None
        frame.f_trace_opcodes = True
        if event == "opcode":
            ran[0] += 1
        return trace

    sys.settrace(trace)
    try:
        # read --interval's device: on a grid, never offline
        run(
            [device("m", 1, offline_after=0, grid=True) if grid else device("m", 1)], rounds=rounds, **options
        )
    finally:
        sys.settrace(None)
    return ran[0]


@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="the budgets are CPython 3.11's bytecodes")
@pytest.mark.parametrize(("published", "budget"), [(False, 305), (True, 417)])
def test_a_poll_that_changes_nothing_costs_the_engine_little(published, budget):
    """Issue 41.9: read --interval (unpublished) and poll (published) run on the engine, whose
    work for a poll that answered and changes no state is its turns (one waits for the slot),
    its slot, the read, its counts and its Poll record; the rules of what did not happen
    (offline, back-off, rounds, overrun, other groups' deadlines) cost little.  The engine ran
    789 and 888 bytecodes a poll; 489 and 541 once a poll's set-up was made once, a waiting turn
    asked the devices' clocks rather than a list of the devices made twice, and a device of no
    groups carried no Pace; 400 and 465 once a link of one group turned a loop of its own, a
    poll that changed no state settled without the rules of a change, and a start on time
    noted nothing; 381 and 462 once a link whose groups are on a grid (read --interval's, whose
    device is counted here) timed no overruns, and a group's cut-in was made once; 370 and 455 once a device that answered and stays
    online was only stamped, and the hook run as a poll's request leaves asked nothing; 359 and 455 once the client came
    to a poll from its turn, and read --interval's poll of one request was not timed twice; 353 and 447 once an overrun was
    flagged as it was counted and what follows a poll (--lenient's deviations, --reconnect-each,
    --pause) asked only by a poll that failed or a link that has it; 349 and 443 once a poll
    was settled straight to its report; 331 and 421 once a Poll was a tuple made in C; 344 and 435, fewer instructions, once
    the callables a poll calls were read as attributes first (the interpreter leaves a call of a
    worker's callable attribute generic); 325 and 414 once a turn that waits waited for the slot
    it had found, not asking it again; 307 and 419 once read --interval's poll that changed
    nothing was handed over as its time and readings, with no Poll (poll's pays the question
    whether it is such a worker); 305 and 417 once a poll's read was bound to its link once a
    run; 307 and 419, fewer instructions, once a turn jumped back unconditionally (the loop is
    specialized in its one call: tests/link/test_transaction_cost.py); 310 and 422 once a group
    of no slots (--interval 0: not counted here) was not asked its next slot, which it has not,
    every poll; 306 and 418 once a turn asked the run's stop by an attribute, not a call
    (``Stop.asked``); 304 and 416 once a turn began at the time the poll before it ended, not
    reading the clock again.  Counted, not timed: a loaded machine moves a rate, not a count."""
    # read --interval's device is on a grid, its poll of one request timed by its round trip, and
    # a poll that changes nothing handed over as its time and readings
    options = {"published": published, "timed": published}
    if not published:
        options["answered"] = lambda when, readings: None
    each = (
        _engine_bytecodes(120, not published, **options) - _engine_bytecodes(20, not published, **options)
    ) / 100
    assert each <= budget, f"the engine ran {each:.0f} bytecodes a poll"
