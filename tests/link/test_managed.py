"""The managed link (mbtool.link.managed) sans-IO, on a fake clock: the one place a link is
opened, opened again when lost, backed off by the one rule, handed its --pause, and judged
lost or not (issue 41, point 1).  No socket, no thread: each test takes milliseconds."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import pytest

from mbtool.codec.errors import FrameError, ModbusException
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link import stats as link_stats
from mbtool.link.managed import Backoff, ManagedLink, link_lost
from mbtool.link.stats import Stats
from mbtool.link.transport import ConnectionClosed


class Clock:
    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


class FakeClient:
    """What the managed link asks of a Client: execute, attempts, rtt, ended_at."""

    def __init__(self, outcomes: list) -> None:
        self.outcomes = outcomes
        self.attempts = 0
        self.rtt = None
        self.ended_at = float("-inf")

    def execute(self, unit, request):
        self.attempts = 1
        outcome = self.outcomes.pop(0) if self.outcomes else "reply"
        if isinstance(outcome, BaseException):
            self.rtt = None
            raise outcome
        self.rtt = 0.01
        self.ended_at = 7.0
        return outcome


class Opener:
    """``open_link`` for the managed link: each open takes the next of ``opens`` (a
    FakeClient, or an error to raise), and records when it was asked and what it closed."""

    def __init__(self, clock: Clock, opens: list) -> None:
        self.clock = clock
        self.opens = list(opens)
        self.asked: list[float] = []
        self.closed = 0
        self.clients: list[FakeClient] = []

    @contextmanager
    def __call__(self):
        self.asked.append(self.clock.now)
        item = self.opens.pop(0) if self.opens else FakeClient([])
        if isinstance(item, BaseException):
            raise item
        self.clients.append(item)
        try:
            yield item
        finally:
            self.closed += 1


def managed(opens: list, first: float = 1.0, longest: float | None = None, stats=None):
    clock = Clock()
    opener = Opener(clock, opens)
    return ManagedLink(opener, Backoff(first, longest), stats, clock), opener, clock


@pytest.mark.parametrize(
    ("error", "lost"),
    [
        (ConnectionClosed("the device closed the connection"), True),
        (ConnectionFailed("cannot connect"), True),
        (BrokenPipeError(32, "Broken pipe"), True),
        (NoResponse("no response within 1 s"), False),
        (FrameError("bad CRC"), False),
        (ModbusException(3, 2), False),
    ],
)
def test_one_judgement_of_a_lost_link(error, lost):
    assert link_lost(error) is lost


def test_the_back_off_doubles_from_first_up_to_longest_and_starts_again():
    backoff = Backoff(2.0, 10.0)
    assert [backoff.failed() for _ in range(5)] == [2.0, 4.0, 8.0, 10.0, 10.0]
    backoff.reset()
    assert backoff.failed() == 2.0
    assert [Backoff(0.5).failed() for _ in range(3)] == [0.5, 0.5, 0.5]  # no longest: a constant wait


def test_the_link_opens_at_the_first_transaction_and_is_kept():
    link, opener, _ = managed([FakeClient(["a", "b"])])
    assert link.client is None and opener.asked == []
    assert link.execute(1, "read") == "a"
    assert link.execute(1, "read") == "b"
    assert len(opener.asked) == 1 and link.opens == 1


def test_a_lost_link_is_closed_and_opened_again_one_first_wait_after_it_was_opened():
    link, opener, clock = managed([FakeClient([ConnectionClosed("closed")]), FakeClient([])], first=1.0)
    with pytest.raises(ConnectionClosed):
        link.execute(1, "read")
    assert link.client is None and opener.closed == 1
    clock.now += 0.25
    link.wait()
    assert clock.sleeps == [0.75]  # a second from the open before, not from the loss
    assert link.execute(1, "read") == "reply" and opener.asked == [100.0, 101.0]


def test_a_link_that_served_a_while_is_opened_again_at_once():
    link, _, clock = managed([FakeClient([ConnectionClosed("closed")])], first=1.0)
    link.open()
    clock.now += 30.0
    with pytest.raises(ConnectionClosed):
        link.execute(1, "read")
    link.wait()
    assert clock.sleeps == []


def test_silence_and_bad_frames_keep_the_link():
    link, opener, _ = managed([FakeClient([NoResponse("silence"), FrameError("bad CRC"), "c"])])
    for error in (NoResponse, FrameError):
        with pytest.raises(error):
            link.execute(1, "read")
    assert link.execute(1, "read") == "c" and len(opener.asked) == 1 and opener.closed == 0


def test_opens_that_fail_in_a_row_back_off_doubling_and_an_oserror_is_a_connection_failure():
    refused = ConnectionRefusedError(111, "Connection refused")
    link, opener, clock = managed([refused, refused, refused, FakeClient([])], first=2.0, longest=5.0)
    waits = []
    for _ in range(3):
        link.wait()
        with pytest.raises(ConnectionFailed, match="Connection refused"):
            link.open()
        waits.append(link.ready_at - clock.now)
    assert waits == [2.0, 4.0, 5.0] and link.failures == 3
    link.wait()
    link.open()
    assert opener.asked == [100.0, 102.0, 106.0, 111.0]
    assert link.backoff.wait == 0.0  # an open that succeeds starts the count again


def test_a_link_closed_on_purpose_is_opened_again_at_once_and_keeps_its_pause():
    link, opener, clock = managed([FakeClient([]), FakeClient([])], first=1.0)
    link.execute(1, "read")
    link.drop(on_purpose=True)  # --reconnect-each
    link.wait()
    assert clock.sleeps == []
    link.open()
    assert opener.clients[1].ended_at == 7.0  # the new client waits --pause after the last reply


def test_each_transaction_is_counted_where_stats_says():
    stats = Stats()
    link, _, _ = managed([FakeClient(["a", NoResponse("silence"), ConnectionClosed("closed")])], stats=stats)
    link.execute(1, "read")
    for _ in range(2):
        with pytest.raises(NoResponse):
            link.execute(1, "read")
    assert (stats.outcomes["answered"], stats.outcomes["timeout"], stats.outcomes["link_lost"]) == (1, 1, 1)
    assert link.attempts == 1 and link.rtt is None


def test_close_closes_for_good_and_twice_is_harmless():
    link, opener, _ = managed([FakeClient([])])
    link.open()
    link.close()
    link.close()
    assert opener.closed == 1 and link.client is None


def test_a_transaction_is_counted_in_one_place():
    """Issue 41: ManagedLink.execute counts each transaction it carries; link.stats.Counted,
    which counted a bare client's the same way by a copy of the rule, is gone (every command
    takes its link from a ManagedLink, and the tests count through it too)."""
    assert not hasattr(link_stats, "Counted")
    sources = [path.read_text() for path in (Path(__file__).resolve().parents[2] / "mbtool").rglob("*.py")]
    assert sum(text.count(".answered(client.attempts") for text in sources) == 1
