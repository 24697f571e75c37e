"""read --interval's polls (mbtool.plant.polling.poll: a plant of one device) in-process: its schedule, the slots it skips, the
failures it counts, a lost link opened again, --pause across a new link and the summary's
figures.

The engine's own clock is a fake one (``polling.Clock``: its slots and waits take no time); the
link is ``fake://``, the simulated device in-process with failures the test scripts into it
poll by poll.  The client keeps the real clock: only a silent poll waits its (short) timeout,
and the --pause test measures real gaps.
"""

from __future__ import annotations

import time

import pytest

import mbtool.link
from mbtool.cli.commands.read import polling_figures, polling_summary
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.device.sim import SimTransport
from mbtool.errors import ConnectionFailed, ExitCode, UsageError, Verdict
from mbtool.link.connection import Connection
from mbtool.link.transport import ConnectionClosed
from mbtool.plant import polling

REQUEST = ReadHoldingRegisters(0, 2)  # the demo device: holding register N holds N
TIMEOUT = 0.05  # real seconds a silent poll waits; the fake clock's reopen wait is this too


class Clock:
    """The loop's ``time``: monotonic seconds that move only when slept on (or when the fake
    device takes its time), and a wall clock that follows them."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return 1_700_000_000.0 + self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds

    def wait(self, stop, seconds: float) -> None:  # the engine's wait for a slot or a back-off
        self.sleep(seconds)


class Bus:
    """What the fake:// links do, poll by poll: ``script`` holds one step a request (``reply``,
    ``silent``, ``lost``: the peer closes the link, ``slow N``: a reply N seconds later on the
    loop's clock, ``interrupt``: Ctrl-C), then replies.  Records when each link opened and each
    request left, on the loop's clock and on the real one."""

    def __init__(self, clock: Clock, script: list[str]) -> None:
        self.clock = clock
        self.script = list(script)
        self.opened: list[float] = []
        self.closed = 0
        self.requests: list[float] = []  # the loop's clock
        self.real_requests: list[float] = []  # time.monotonic()

    def open(self, framer_name: str) -> SimTransport:
        self.opened.append(self.clock.now)
        return Link(self, framer_name)


class Link(SimTransport):
    def __init__(self, bus: Bus, framer_name: str) -> None:
        super().__init__(framer_name)
        self.bus = bus

    def write(self, data: bytes) -> None:
        self.bus.requests.append(self.bus.clock.now)
        self.bus.real_requests.append(time.monotonic())
        step = self.bus.script.pop(0) if self.bus.script else "reply"
        if step == "interrupt":
            raise KeyboardInterrupt
        if step == "lost":
            raise ConnectionClosed("the device closed the connection")
        if step.startswith("slow "):
            self.bus.clock.now += float(step.split()[1])
        if step != "silent":
            super().write(data)

    def close(self) -> None:
        self.bus.closed += 1


class Shown:
    """What the loop shows: each reply held then written, each failure, in order."""

    def __init__(self) -> None:
        self.held = None
        self.shown: list[tuple] = []
        self.closed = False

    def hold(self, when: float, reply) -> None:
        self.held = (when, reply)

    def write(self) -> None:
        if self.held is not None:
            when, reply = self.held
            self.shown.append(("reply", when, reply.registers))
            self.held = None

    def failure(self, when: float, number: int, error: BaseException) -> None:
        self.shown.append(("failure", when, number, type(error).__name__))

    def close(self) -> None:
        self.write()  # the last reply held, as the CLI's output shows it at the end
        self.closed = True


@pytest.fixture
def clock(monkeypatch) -> Clock:
    fake = Clock()
    monkeypatch.setattr(polling, "Clock", fake)
    return fake


@pytest.fixture
def bus(monkeypatch, clock):
    """``make(script)``: a Bus behind fake:// for this test."""

    def make(script: list[str] = ()) -> Bus:
        made = Bus(clock, script)
        monkeypatch.setitem(mbtool.link.IN_PROCESS, "fake", made.open)
        return made

    return make


def run(connection: Connection, interval: float, polls: int) -> tuple[Verdict, Shown, dict]:
    """poll() to its end: the record it returns in words (the Verdict the command ends with),
    what it showed, the figures (--stats json)."""
    shown = Shown()
    polled = polling.poll(connection, REQUEST, shown, interval, polls)
    assert shown.closed
    return polling_summary(polled), shown, polling_figures(polled)


def link(**options) -> Connection:
    return Connection(port="fake://", timeout=TIMEOUT, **options)


def test_polls_keep_their_slots_on_the_monotonic_clock(clock, bus):
    fake = bus()
    summary, shown, _ = run(link(), interval=1.0, polls=4)
    start = fake.opened[0]
    assert fake.requests == [start, start + 1.0, start + 2.0, start + 3.0]
    assert [item[0] for item in shown.shown] == ["reply"] * 4
    assert shown.shown[0][2] == (0, 1)
    # Each poll stamped with the wall clock's time of its request.
    assert [item[1] for item in shown.shown] == [clock.time() - 3.0 + k for k in range(4)]
    assert summary.exit_code == ExitCode.OK
    assert str(summary).startswith("polls 4, replies 4, partial 0, timeouts 0, errors 0, skipped 0, ")
    assert ", 1 polls/s; " in str(summary)


def test_a_poll_that_overruns_its_slot_skips_the_slots_it_missed(bus):
    fake = bus(["reply", "slow 2.5", "reply"])
    summary, _, figures = run(link(), interval=1.0, polls=3)
    start = fake.opened[0]
    # The second poll ends 3.5 s in: slots 2 and 3 have passed, the third poll takes slot 4.
    assert fake.requests == [start, start + 1.0, start + 4.0]
    assert figures["skipped"] == 2 and "skipped 2," in str(summary)


def test_the_last_poll_never_counts_slots_skipped_after_it(bus):
    bus(["reply", "slow 5"])
    summary, _, figures = run(link(), interval=1.0, polls=2)
    assert figures["skipped"] == 0 and summary.exit_code == ExitCode.OK


def test_failures_are_counted_and_polling_goes_on(bus):
    fake = bus(["reply", "silent", "reply", "silent"])
    summary, shown, figures = run(link(), interval=1.0, polls=4)
    assert [item[0] for item in shown.shown] == ["reply", "failure", "reply", "failure"]
    assert [item[2] for item in shown.shown if item[0] == "failure"] == [2, 4]  # poll numbers
    assert (figures["polls"], figures["replies"], figures["timeouts"], figures["errors"]) == (4, 2, 2, 0)
    assert (figures["transactions"], figures["answered"], figures["timeout"]) == (4, 2, 2)
    assert summary.exit_code == ExitCode.TIMEOUT
    assert str(summary).startswith("polls 4, replies 2, partial 0, timeouts 2, errors 0, skipped 0, ")
    assert len(fake.opened) == 1  # silence is no lost link: the same link all along


def test_the_code_is_the_last_failures_even_when_replies_came_after_it(bus):
    bus(["silent", "reply", "reply"])
    summary, _, _ = run(link(), interval=1.0, polls=3)
    assert summary.exit_code == ExitCode.TIMEOUT


def test_a_lost_link_is_opened_again_one_timeout_after_it_was_opened(clock, bus):
    fake = bus(["reply", "lost", "reply", "reply"])
    summary, shown, figures = run(link(), interval=0, polls=4)
    assert len(fake.opened) == 2 and fake.closed >= 1
    assert fake.opened[1] >= fake.opened[0] + TIMEOUT  # not hammered, even back to back
    assert [item[0] for item in shown.shown] == ["reply", "failure", "reply", "reply"]
    assert shown.shown[1][3] == "ConnectionClosed"
    assert (figures["replies"], figures["timeouts"], figures["link_lost"]) == (3, 1, 1)
    assert summary.exit_code == ExitCode.TIMEOUT  # the peer closed it: no reply can come


def test_a_link_that_cannot_be_opened_is_a_failed_poll_and_tried_again(monkeypatch, clock, bus):
    fake = bus()
    opens = []

    def refusing_once(framer_name):
        opens.append(clock.now)
        if len(opens) == 1:
            raise ConnectionFailed("cannot open fake://: not there yet")
        return fake.open(framer_name)

    monkeypatch.setitem(mbtool.link.IN_PROCESS, "fake", refusing_once)
    summary, shown, figures = run(link(), interval=0, polls=2)
    assert [item[0] for item in shown.shown] == ["failure", "reply"]
    assert opens[1] >= opens[0] + TIMEOUT
    assert (figures["errors"], figures["replies"]) == (1, 1)
    assert summary.exit_code == ExitCode.CONNECTION


def test_pause_is_kept_across_a_new_link(bus):
    """--pause with --reconnect-each: each poll has a link of its own, and its request still
    waits the pause after the reply on the link before (the new client is told when that was)."""
    pause = 0.2
    fake = bus()
    summary, _, _ = run(link(pause=pause, reconnect_each=True), interval=0, polls=3)
    assert len(fake.opened) == 3 and fake.closed == 3
    gaps = [
        later - earlier for earlier, later in zip(fake.real_requests, fake.real_requests[1:], strict=False)
    ]
    assert all(gap >= pause for gap in gaps), gaps
    assert summary.exit_code == ExitCode.OK


def test_interrupted_before_any_poll_is_130_and_after_one_the_polls_verdict(bus):
    bus(["interrupt"])
    summary, _, figures = run(link(), interval=1.0, polls=3)
    assert summary.exit_code == ExitCode.INTERRUPTED and figures["interrupted"] is True
    assert str(summary).startswith("interrupted; polls 0, ")

    bus(["reply", "interrupt"])
    summary, shown, figures = run(link(), interval=1.0, polls=3)
    assert summary.exit_code == ExitCode.OK and figures["polls"] == 1
    assert str(summary).startswith("interrupted; polls 1, replies 1, ")
    assert [item[0] for item in shown.shown] == ["reply"]  # the poll held is shown at the end


def test_the_summarys_figures(bus):
    bus(["reply", "silent", "reply"])
    summary, _, figures = run(link(), interval=1.0, polls=3)
    assert {
        key: figures[key] for key in ("polls", "replies", "partial", "timeouts", "errors", "skipped")
    } == {
        "polls": 3,
        "replies": 2,
        "partial": 0,
        "timeouts": 1,
        "errors": 0,
        "skipped": 0,
    }
    assert figures["interrupted"] is False
    per_request, per_poll = figures["latency_ms"]["per_request"], figures["latency_ms"]["per_poll"]
    assert per_request["min"] <= per_request["avg"] <= per_request["max"]
    assert per_poll["min"] <= per_poll["avg"] <= per_poll["max"]
    # +Inf: every reply's round trip, but one that came while mbtool was busy (a loaded machine
    # between its write and its wait), whose arrival is not known: counted untimed instead
    assert figures["rtt_buckets"][-1][1] + figures["rtt_untimed"] == 2
    text = str(summary)
    assert "latency per request min/avg/max " in text and " ms, per poll " in text
    assert ", 1 polls/s; " in text  # 3 polls over the 2 s from the first to the last
    assert "answered 2" in text and "timeout 1" in text


def test_no_figures_before_the_first_reply(bus):
    bus(["silent"])
    summary, _, figures = run(link(), interval=1.0, polls=1)
    assert figures["latency_ms"] == {"per_request": None, "per_poll": None}
    assert "latency per request min/avg/max -, per poll -;" in str(summary)
    assert "polls/s" not in str(summary)


def test_a_request_the_link_cannot_carry_is_an_error_before_anything_is_sent(bus):
    fake = bus()
    shown = Shown()
    with pytest.raises(UsageError):
        polling.poll(link(unit=0), REQUEST, shown, 1.0, 3)  # a read to the broadcast unit
    assert fake.requests == [] and shown.closed
