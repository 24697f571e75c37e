"""What a polling transaction costs mbtool's master side, counted in bytecodes (issue 41, point
9): the managed link, the client, the exchange, the framer and the reply's decoding, a
transaction as ``read --interval`` and the plant make them, with every reply's values new.

Counted, not timed: a loaded machine moves a rate, not a count.  The link answers in process
(no system call to wait on) and the clock steps a microsecond a reading, so the same
transaction runs the same bytecodes every time; ``bench/polling_instructions.py`` counts the
same path's instructions over TCP with callgrind."""

from __future__ import annotations

import dis
import sys
from pathlib import Path

import pytest
from helpers.checks import bytecodes, in_fresh_interpreter, unspecialized

import mbtool
from mbtool.codec.data_access import ReadHoldingRegisters, RegistersResponse
from mbtool.codec.mbap import TcpFramer
from mbtool.link.client import Client
from mbtool.link.connection import Connection
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats
from mbtool.link.transport import Transport
from mbtool.plant import polling
from mbtool.plant.schedule import LinkWorker

COUNT = 10
MBTOOL = str(Path(mbtool.__file__).parent)


class SteppingClock:
    """A monotonic clock that moves a microsecond each time it is read."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += 1e-6
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class Answering(Transport):
    """A Modbus TCP device in process: each request answered at once with its transaction id and
    registers whose values are new every reply."""

    serial_line = False

    def __init__(self) -> None:
        self.step = 0
        self.reply = b""

    def write(self, adu: bytes) -> None:
        self.step += 1
        data = b"".join((self.step + i).to_bytes(2, "big") for i in range(COUNT))
        self.reply = adu[:4] + (3 + 2 * COUNT).to_bytes(2, "big") + bytes([adu[6], 3, 2 * COUNT]) + data

    def read(self, timeout: float) -> bytes:
        reply, self.reply = self.reply, b""
        return reply

    def input_waiting(self) -> bool:
        return bool(self.reply)


def _polling(requests: list) -> tuple:
    """One poll of ``requests`` (a map's reads, in turn) as polling makes it, the replies it
    keeps and the link's statistics."""
    clock = SteppingClock()
    client = Client(Answering(), TcpFramer(), clock=clock, sleep=clock.sleep)
    stats = Stats()
    managed = ManagedLink(lambda: _opened(client), Backoff(1.0), stats)
    replies: list = []

    def poll() -> None:
        client.while_waiting = lambda: None  # polling's: the poll before shown
        for request in requests:
            replies.append(managed.execute(1, request))

    return poll, replies, stats


def _polled(requests: list) -> tuple[int, list, Stats]:
    """Polls of ``requests`` as polling makes them: the median bytecodes of mbtool's a
    transaction, the replies and the link's statistics."""
    poll, replies, stats = _polling(requests)
    for _ in range(3):  # the link opened, the requests' frames and predictions made
        poll()
    counts = sorted(bytecodes(poll, MBTOOL) for _ in range(21))
    return counts[10] // len(requests), replies, stats


def test_a_polled_transaction_with_new_values_costs_the_master_at_most_450_bytecodes():
    """A poll's transaction, as polling makes it (its work while the reply is on its way, the
    managed link counting it), cost 606 bytecodes of the managed link, the client, the exchange,
    the framer and the decoding: what is the same for every poll of a request (its frame but
    the transaction id, its reply's prediction and decoder) is now worked out once a request,
    and what never changes for a link once a link."""
    ran, replies, stats = _polled([ReadHoldingRegisters(0, COUNT)])
    assert replies[-1] == RegistersResponse(3, tuple(range(24, 24 + COUNT)))  # new values, each read
    assert stats.outcomes["answered"] == 24 and stats.untimed == 0  # every one counted and timed
    assert ran <= 450, f"a transaction ran {ran} bytecodes of mbtool's"


def test_the_requests_of_a_map_taking_turns_are_each_worked_out_once():
    """A map read is several requests, each sent in turn every poll (a plant's devices take
    turns on a link too): each one's frame, prediction and decoder are kept, not worked out
    again whenever another request went between (647 bytecodes a transaction when they were)."""
    requests = [ReadHoldingRegisters(100 * n, COUNT) for n in range(3)]
    ran, replies, stats = _polled(requests)
    assert [reply.registers[0] for reply in replies[-3:]] == [70, 71, 72]  # each its own, new
    assert stats.outcomes["answered"] == 72 and stats.untimed == 0
    assert ran <= 500, f"a transaction ran {ran} bytecodes of mbtool's"


def _unspecialized() -> list[str]:
    """The attribute reads of mbtool's a polled transaction left generic (run in a fresh
    interpreter)."""
    poll, _, _ = _polling([ReadHoldingRegisters(0, COUNT)])
    return unspecialized(poll, MBTOOL)


# What 3.11 specializes (the bench's interpreter): 3.12 specializes more (class attributes,
# properties), so a read left generic here may not be there.
@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="what is specialized is 3.11's")
def test_every_attribute_a_polled_transaction_reads_is_one_the_interpreter_specializes():
    """A poll's transaction read eleven attributes the generic way, some 1.2k instructions a poll
    (callgrind, the client in process): the exchange's worked-out request and its reply's
    prediction were named tuples, two of their fields called as methods, and the framer's
    waiting_for_silence a class attribute."""
    assert in_fresh_interpreter("link.test_transaction_cost", "_unspecialized") == []


class _opened:
    """open_link's context manager, giving the client already made."""

    def __init__(self, client: Client) -> None:
        self.client = client

    def __enter__(self) -> Client:
        return self.client

    def __exit__(self, *exc) -> None:
        return None


class _Shown:
    """polling.Shown that keeps each poll's reply: the output's cost is counted elsewhere
    (tests/cli/test_poll_cost.py)."""

    def __init__(self) -> None:
        self.replies: list = []

    def hold(self, when: float, reply) -> None:
        self.replies.append(reply)

    def write(self) -> None:
        pass

    def failure(self, when: float, number: int, error: BaseException) -> None:
        raise AssertionError(error)

    def close(self) -> None:
        pass


def test_read_interval_on_the_engine_costs_a_poll_of_one_request_at_most_199_bytecodes(monkeypatch):
    """read --interval 0, a plant of one device (plant/polling.py on plant/schedule.py's
    LinkWorker: the poll's turn, its settling, its record handed to the tally, its request's
    time taken as it leaves): some 400 bytecodes a poll of the engine's own when read --interval
    moved onto it, 255 since (a link of one group turns its own loop; a poll that changes
    nothing settles without the rules of a change of state; the Poll made in C), 252 then, 243
    once the tally asked the worker at the end what it counts already (the polls' times), 230
    once a group of no slots (--interval 0) was not worked out a next slot it does not have;
    245, fewer instructions, once the callables a poll calls were read as attributes first (the
    test below); 207 once a poll that changed nothing was handed to the output as its time and
    reply, with no Poll made and read back by the tally; 205 once a poll of one request was
    that request's transaction, bound once a run (a partial, no reader's read a poll); 206, fewer
    instructions, once a turn jumped back unconditionally (the test below); 198 once a group of
    no slots was not asked its next slot every poll.
    main's own loop, which it replaces, ran 71."""
    clock = SteppingClock()
    monkeypatch.setattr(
        polling, "open_client", lambda *args, **kwargs: _opened(Client(Answering(), TcpFramer(), clock=clock))
    )
    plant = str(Path(polling.__file__).parent)

    def own(polls: int) -> tuple[int, polling.Polled, _Shown]:
        shown = _Shown()
        run: list[polling.Polled] = []
        ran = bytecodes(
            lambda: run.append(
                polling.poll(
                    Connection(port="tcp://192.0.2.1"), ReadHoldingRegisters(0, COUNT), shown, 0, polls
                )
            ),
            plant,
        )
        return ran, run[0], shown

    few, _, _ = own(10)
    many, polled, shown = own(30)
    assert polled.polls == polled.replies == 30 and polled.exit_code == 0
    assert shown.replies[-1] == RegistersResponse(3, tuple(range(30, 30 + COUNT)))
    ran = (many - few) / 20
    assert ran <= 199, f"the engine ran {ran} bytecodes a poll"


# What the engine runs every poll of read --interval (plant/schedule.py)
_ENGINE_EACH_POLL = (
    "LinkWorker._work_alone",
    "LinkWorker._poll",
    "LinkWorker._request_sent",
    "LinkWorker._settle",
    "GroupState.next",
    "DeviceState.answered",
)


def _engine_unspecialized() -> list[str]:
    """The attribute reads of the engine's a poll of read --interval left generic (run in a
    fresh interpreter): runs of a few polls, the engine's set-up for each left out."""
    clock = SteppingClock()
    polling.open_client = lambda *args, **kwargs: _opened(Client(Answering(), TcpFramer(), clock=clock))

    def run() -> None:
        polling.poll(Connection(port="tcp://192.0.2.1"), ReadHoldingRegisters(0, COUNT), _Shown(), 0, 3)

    # Looked at once, not after each of the misses that make 3.11 give a read up: every run
    # makes a new worker, and a look-up of its methods, keyed by that instance's own table,
    # misses in every new run where a real run's one worker's does not.
    found = unspecialized(run, str(Path(polling.__file__).parent), recheck=False)
    return [line for line in found if line.startswith(_ENGINE_EACH_POLL)]


@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="what is specialized is 3.11's")
def test_every_attribute_the_engine_reads_a_poll_is_one_the_interpreter_specializes():
    """A worker has more attributes than an instance's shared keys hold, and the interpreter
    leaves a call of its methods, or of a callable it keeps, generic (some hundred instructions
    each): a poll looked up the group's reader and its read, the clock's monotonic (twice),
    the worker's _settle, and as its request left its wall clock and the output's hook, the
    generic way."""
    assert in_fresh_interpreter("link.test_transaction_cost", "_engine_unspecialized") == []


def _engine_loop_generic() -> list[str]:
    """The attribute reads and writes of a turn of read --interval's loop (LinkWorker._work_alone)
    left generic after one run of 100 polls (run in a fresh interpreter): the loop is called once
    a run, so its turns are all that can make the interpreter specialize it."""
    clock = SteppingClock()
    polling.open_client = lambda *args, **kwargs: _opened(Client(Answering(), TcpFramer(), clock=clock))
    polling.poll(Connection(port="tcp://192.0.2.1"), ReadHoldingRegisters(0, COUNT), _Shown(), 0, 100)
    turn = ("turns", "client", "due", "asked")  # what a turn that polls reads and writes
    return [
        f"{op.opname} {op.argval}"
        for op in dis.get_instructions(LinkWorker._work_alone, adaptive=True)
        if op.argval in turn
        and (op.opname in ("LOAD_ATTR", "LOAD_METHOD", "STORE_ATTR") or op.opname.endswith("_ADAPTIVE"))
    ]


@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="what is specialized is 3.11's")
def test_the_engine_s_loop_is_specialized_in_its_one_call_a_run():
    """Python 3.11 specializes a function once it has been called, or has jumped back
    unconditionally, a few times; a while's test that jumps back does not count.  The engine's
    loop, called once a run and turned by its test, ran every turn's reads the generic way for
    the whole run: 1.5k instructions a poll of read --interval 0 (callgrind, 60.2k -> 58.7k)."""
    assert in_fresh_interpreter("link.test_transaction_cost", "_engine_loop_generic") == []
