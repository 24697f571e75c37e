"""A peer that floods garbage (a broken gateway streaming noise) cannot hang mbtool (issue 13.1).

The flooder answers the first bytes of each connection with noise, as fast as the socket
takes it, until the test stops it.  Every command must end within its deadlines:
timeout × (retries + 1) a transaction, plus Python's start-up and LATE (a loaded machine's
margin; a command that let the flood hold it would run until the test's timeout).  A peer that
babbles endlessly after any request is the resync's (codec/rtu.py) worst case: it too ends at
the deadline with one error.
"""

from __future__ import annotations

import contextlib
import random
import select
import socket
import threading
import time

import pytest
from helpers.checks import assert_one_error_line
from helpers.run import run_mbtool

pytestmark = pytest.mark.timeout(60)

NOISE = random.Random(131).randbytes(1 << 20)
TIMEOUT = 0.5
RETRIES = 2
# Bytes the flood must have sent, unless it filled mbtool's socket (came faster than read): far
# more than the framer holds (64 KiB), however slowly a loaded machine runs the flooder.
FLOOD_FLOOR = 4 << 20
LATE = 2.0  # seconds past the deadlines a loaded machine may take to end a process


class Flooder:
    def __init__(self) -> None:
        self.server = socket.socket()
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(8)
        self.port = self.server.getsockname()[1]
        self.stop = threading.Event()
        self.sent = 0
        self.saturated = False  # the flood filled mbtool's socket: it came faster than read
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            if select.select([self.server], [], [], 0.05)[0]:
                conn, _ = self.server.accept()
                threading.Thread(target=self._flood, args=(conn,), daemon=True).start()

    def _flood(self, conn: socket.socket) -> None:
        with conn:
            if not select.select([conn], [], [], 5)[0]:
                return
            conn.recv(512)  # the first request: from now on, noise
            conn.setblocking(False)
            try:
                while not self.stop.is_set():
                    try:
                        self.sent += conn.send(NOISE)
                    except BlockingIOError:
                        # mbtool's socket is full: the flood outruns its reading. Wait (a
                        # loaded machine may pause mbtool) until it reads, closes or the test ends.
                        self.saturated = True
                        select.select([], [conn], [], 0.2)
            except OSError:  # mbtool closed the link
                pass

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        self.server.close()


@pytest.fixture
def flooder():
    peer = Flooder()
    yield peer
    peer.close()


@pytest.mark.parametrize(
    "scheme, options",
    [("tcp", ()), ("tcp", ("--framer", "rtu")), ("socket", ())],
    ids=["mbap", "rtu-over-tcp", "socket"],
)
def test_a_read_under_a_garbage_flood_ends_on_time(flooder, start_up, scheme, options):
    res = run_mbtool(
        "read-holding-registers", "0", "2",
        "-p", f"{scheme}://127.0.0.1:{flooder.port}",
        "-t", str(TIMEOUT), "--retries", str(RETRIES), *options,
    )  # fmt: skip
    assert res.returncode == 5, str(res)
    assert "garbage" in res.stderr or "error" in res.stderr, str(res)
    assert res.elapsed <= TIMEOUT * (RETRIES + 1) + LATE + start_up, res.elapsed
    # Either way the flood was as fast as mbtool could take it, or more than the floor.
    assert flooder.saturated or flooder.sent >= FLOOD_FLOOR, f"the flood sent only {flooder.sent} bytes"


def test_polling_under_a_garbage_flood_ends_on_time(flooder, start_up):
    polls = 2
    res = run_mbtool(
        "read-holding-registers", "0", "2", "-p", f"tcp://127.0.0.1:{flooder.port}",
        "-t", str(TIMEOUT), "--retries", str(RETRIES), "--interval", "0", "--polls", str(polls),
    )  # fmt: skip
    assert res.returncode == 5, str(res)
    assert "polls 2, replies 0" in res.stderr, str(res)
    assert res.elapsed <= polls * TIMEOUT * (RETRIES + 1) + LATE + start_up, res.elapsed


def test_scan_under_a_garbage_flood_ends_on_time(flooder, start_up):
    res = run_mbtool("scan", "-p", f"tcp://127.0.0.1:{flooder.port}", "--units", "1-3", "-t", str(TIMEOUT))
    assert res.returncode == 5, str(res)  # only garbled answers came
    assert res.elapsed <= 3 * TIMEOUT + LATE + start_up, res.elapsed


class Babbler:
    """A TCP peer that sends random bytes, never a frame, as fast as they are read, until closed."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.sock.settimeout(5)
        self.port = self.sock.getsockname()[1]
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._babble, daemon=True)
        self._thread.start()

    def _babble(self) -> None:
        rng = random.Random(3)
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        with conn:
            while not self._stop.is_set():
                try:
                    conn.sendall(rng.randbytes(4096))
                except OSError:
                    return
                self.sent += 4096

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self.sock.close()
        self._thread.join(timeout=2)


@pytest.fixture
def babbler():
    peer = Babbler()
    yield peer
    peer.close()


def test_endless_garbage_ends_at_the_deadline_with_one_error(babbler):
    start = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "-p", f"socket://127.0.0.1:{babbler.port}", "-t", "0.5")
    elapsed = time.monotonic() - start
    assert res.returncode in (3, 5), str(res)
    assert_one_error_line(res, res.returncode)
    assert elapsed < 0.5 + LATE + 1.5, f"took {elapsed:.2f} s with -t 0.5\n{res}"
    assert babbler.sent > 64 * 1024, "the peer should have sent more than the framer holds"
