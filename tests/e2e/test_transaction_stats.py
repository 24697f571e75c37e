"""One classification of every transaction (issue 32): link.managed.ManagedLink, which counts
each transaction, around mbtool's own Client, against peers that produce each outcome -- pymodbus's device, ``mbtool serve`` with its
faults, raw responders on loopback, and a pseudo-terminal bus whose device end the test plays,
injecting corrupt bytes, replies for another unit and delays.

Each transaction ends as exactly one of answered, exception (by code), timeout, corrupt, not
ours or link lost; an answer that took a retry is also a retry that recovered; every reply's
round-trip time is in the histogram.
"""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty
from contextlib import nullcontext

import pytest
from helpers.frames import rtu
from helpers.ptys import PtyPair
from helpers.served import serve
from helpers.sockets import CLOSE

from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.errors import KNOWN_ERRORS
from mbtool.link.connection import Connection, connection_of, open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import OUTCOMES, Stats

pytestmark = pytest.mark.timeout(60)

READ = ReadHoldingRegisters(0, 1)
REPLY = rtu(bytes.fromhex("0103020064"))  # unit 1: one register, 100
CORRUPT = REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])  # the same with its CRC broken
OTHER_UNIT = rtu(bytes.fromhex("0203020064"))  # whole and valid, from unit 2


class SentFrames:
    """The client's trace, counting the requests that went out: the test's own count of each
    transaction's attempts, apart from the client's."""

    def __init__(self) -> None:
        self.count = 0

    def sent(self, adu: bytes) -> None:
        self.count += 1

    def received(self, adu: bytes, note: str = "") -> None:
        pass

    def rejected(self, data: bytes, error) -> None:
        pass


def transact(connection: Connection, times: int, unit: int = 1) -> tuple[Stats, list[tuple[str, int]]]:
    """``times`` reads of one register through the managed link, which counts them: the stats, and what each transaction
    was by the test's own look (the error's class name or "reply", and the requests it sent)."""
    stats = Stats()
    seen = []
    with open_client(connection) as client:
        sent = SentFrames()
        client.trace = sent
        counted = ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats).execute
        for _ in range(times):
            before = sent.count
            try:
                counted(unit, READ)
            except KNOWN_ERRORS as error:
                seen.append((type(error).__name__, sent.count - before))
            else:
                seen.append(("reply", sent.count - before))
    return stats, seen


def only(stats: Stats, outcome: str, count: int) -> None:
    """Every transaction ended as ``outcome``, and as nothing else."""
    assert stats.transactions == count
    assert {o: stats.outcomes[o] for o in OUTCOMES} == {o: count if o == outcome else 0 for o in OUTCOMES}


# --- over TCP: pymodbus's device, mbtool serve's faults, raw responders ---------------------


def test_answered_by_pymodbus_each_with_its_round_trip_in_the_histogram(tcp_device):
    stats, seen = transact(Connection(port=tcp_device.target), 5)
    assert seen == [("reply", 1)] * 5
    only(stats, "answered", 5)
    assert stats.recovered == 0
    assert stats.rtt.count == 5 and stats.rtt.buckets()[-1][1] == 5
    figures = stats.rtt_figures()
    assert 0 < figures["min"] <= figures["avg"] <= figures["max"] < 1.0


def test_an_exception_is_counted_by_its_code_and_its_reply_timed():
    with serve("--exception", "3:2") as server:
        stats, seen = transact(Connection(port=server.target), 3)
    assert seen == [("ModbusException", 1)] * 3
    only(stats, "exception", 3)
    assert dict(stats.exceptions) == {2: 3}
    assert stats.rtt.count == 3  # an exception is the device's reply: it has a round trip
    assert stats.as_dict()["exceptions_by_code"] == {"02": 3}


def test_silence_is_a_timeout_with_no_round_trip():
    with serve("--drop", "1") as server:
        stats, seen = transact(Connection(port=server.target, timeout=0.2, retries=1), 2)
    assert seen == [("NoResponse", 2)] * 2  # each sent twice, answered never
    only(stats, "timeout", 2)
    assert stats.rtt.count == 0 and stats.rtt_figures() is None and stats.recovered == 0


def test_a_bad_crc_from_serve_is_corrupt():
    with serve("--framer", "rtu", "--corrupt", "1") as server:
        stats, seen = transact(Connection(port=server.socket_target, timeout=0.3), 2)
    assert [kind for kind, _ in seen] == ["ChecksumError"] * 2
    only(stats, "corrupt", 2)
    assert stats.rtt.count == 0


def test_a_reply_with_another_transaction_id_is_not_ours(raw_responder):
    def wrong_id(request: bytes) -> bytes:
        tid = struct.unpack(">H", request[:2])[0]
        return struct.pack(">HHHB", (tid + 7) & 0xFFFF, 0, 5, 1) + bytes.fromhex("03020064")

    srv = raw_responder(wrong_id)
    stats, seen = transact(Connection(port=srv.tcp_target, timeout=0.3), 2)
    assert [kind for kind, _ in seen] == ["MismatchError"] * 2
    only(stats, "not_ours", 2)


def test_a_peer_that_hangs_up_is_the_link_lost(raw_responder):
    srv = raw_responder(lambda request: CLOSE)
    stats, seen = transact(Connection(port=srv.tcp_target, timeout=0.5), 1)
    assert [kind for kind, _ in seen] == ["ConnectionClosed"]
    only(stats, "link_lost", 1)


def test_answers_that_took_a_retry_are_retries_that_recovered():
    # --drop 0.5 with a seed: the same replies are dropped on every run.
    with serve("--drop", "0.5", "--seed", "7") as server:
        stats, seen = transact(Connection(port=server.target, timeout=0.2, retries=4), 12)
    retried = [attempts for kind, attempts in seen if kind == "reply" and attempts > 1]
    assert retried, f"seed 7 dropped no reply that a retry then got: {seen}"
    assert stats.recovered == len(retried)
    assert stats.outcomes["answered"] == sum(kind == "reply" for kind, _ in seen)
    assert stats.outcomes["timeout"] == sum(kind == "NoResponse" for kind, _ in seen)
    assert stats.transactions == 12 and stats.rtt.count == stats.outcomes["answered"]


# --- a pseudo-terminal bus, its device end played by the test --------------------------------


class ScriptedDevice:
    """The device end of a PtyPair: each 8-byte request read whole, then answered by the next
    step of ``script``: (seconds to wait, bytes to write or None for silence)."""

    def __init__(self, pair: PtyPair, script: list[tuple[float, bytes | None]]) -> None:
        self.fd = os.open(pair.device_path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.script = list(script)
        self.requests: list[bytes] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _read_request(self, deadline: float) -> bytes:
        data = b""
        while len(data) < 8 and time.monotonic() < deadline:
            ready, _, _ = select.select([self.fd], [], [], 0.05)
            if ready:
                data += os.read(self.fd, 8 - len(data))
        return data

    def _run(self) -> None:
        for delay, reply in self.script:
            request = self._read_request(time.monotonic() + 20)
            if len(request) < 8:
                return
            self.requests.append(request)
            time.sleep(delay)
            if reply is not None:
                os.write(self.fd, reply)

    def close(self) -> None:
        self.thread.join(5)
        os.close(self.fd)


def on_a_bus(script: list[tuple[float, bytes | None]], times: int, **options):
    pair = PtyPair()
    device = ScriptedDevice(pair, script)
    try:
        connection = connection_of(port=pair.mbtool_path, parity="N", timeout=0.4, **options)
        return transact(connection, times)
    finally:
        device.close()
        pair.close()


def test_on_a_serial_bus_every_outcome_is_told_apart():
    stats, seen = on_a_bus(
        [
            (0.0, REPLY),  # answered at once
            # Answered 160 ms after the device read it: a round trip of at least 150 ms as
            # mbtool times it (from its own stamp, which may come a moment after the device
            # read the request), past the 0.1 s bucket.
            (0.16, REPLY),
            (0.0, CORRUPT),  # bad CRC: the wire
            (0.0, OTHER_UNIT),  # whole, but from unit 2
            (0.0, rtu(bytes.fromhex("018303"))),  # exception 03
            (0.0, None),  # silence
        ],
        6,
    )
    assert [kind for kind, _ in seen] == [
        "reply",
        "reply",
        "ChecksumError",
        "MismatchError",
        "ModbusException",
        "NoResponse",
    ]
    assert stats.transactions == 6
    assert {o: stats.outcomes[o] for o in OUTCOMES} == {
        "answered": 2,
        "exception": 1,
        "timeout": 1,
        "corrupt": 1,
        "not_ours": 1,
        "link_lost": 0,
        "connection": 0,
    }
    assert dict(stats.exceptions) == {3: 1}
    assert stats.rtt.count == 3  # the two answers and the exception
    assert stats.rtt.high >= 0.15
    assert dict(stats.rtt.buckets())[0.1] <= 2  # the slow answer is past 0.1 s


def test_on_a_serial_bus_a_reply_after_a_retry_is_a_retry_that_recovered():
    # The first request gets garbage and the second silence; the third (second retry) its reply.
    stats, seen = on_a_bus([(0.0, CORRUPT), (0.0, None), (0.0, REPLY)], 1, retries=2)
    assert seen == [("reply", 3)]
    only(stats, "answered", 1)
    assert stats.recovered == 1


def test_on_a_serial_bus_a_reply_later_than_the_timeout_is_a_timeout():
    stats, seen = on_a_bus([(0.7, REPLY)], 1)
    assert seen == [("NoResponse", 1)]
    only(stats, "timeout", 1)


def test_every_round_trip_the_client_times_is_counted(tcp_device):
    # The client keeps each execute's round trip (polling's latency per request is it too).
    stats = Stats()
    with open_client(Connection(port=tcp_device.target)) as client:
        timed: list[float] = []
        link = ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats)
        for _ in range(3):
            link.execute(1, READ)
            timed.append(client.rtt)
            assert link.rtt == client.rtt > 0
    assert list(stats.rtt.recent) == timed
