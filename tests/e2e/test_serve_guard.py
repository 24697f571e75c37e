"""``mbtool serve`` cannot be locked by idle connections (issue 13 item 9).

A connection that completes no request soon after connecting is closed
(--first-request-timeout), and a newcomer past --max-clients takes the slot of the least
recently used idle connection, those that never completed a request first (the Modbus TCP
implementation guide's connection management).  The attackers are raw sockets that send one
byte and wait; the normal client is pymodbus's, an independent implementation.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time

import pytest
from helpers.checks import closed_by_peer
from helpers.frames import mbap
from helpers.served import PROMPT, pymodbus_tcp, serve, timed_read

pytestmark = pytest.mark.timeout(60)


def one_byte_clients(server, count: int) -> list[socket.socket]:
    """``count`` connections that each send one byte of a request and then wait."""
    socks = []
    for _ in range(count):
        sock = server.connect()
        sock.send(b"\x00")
        socks.append(sock)
    return socks


def test_a_connection_without_a_request_is_closed_after_the_first_request_timeout():
    first = 0.5
    with serve("--first-request-timeout", str(first), "--idle-timeout", "60", quiet=False) as server:
        used = pymodbus_tcp(server)
        try:
            timed_read(used)
            opened = time.monotonic()
            silent = server.connect()
            dripped = one_byte_clients(server, 1)[0]
            assert closed_by_peer(silent, wait=first + 3)
            assert closed_by_peer(dripped, wait=first + 3)
            closed_in = time.monotonic() - opened
            time.sleep(first)
            timed_read(used)  # a client that completed a request keeps its slot past the limit
        finally:
            used.close()
            silent.close()
            dripped.close()
        assert first * 0.9 <= closed_in <= first + 3, closed_in
    log = server.log()  # now the server has stopped and printed its summary
    assert log.count("first-request timeout: no whole request") == 2, log
    assert "1 bytes of one buffered" in log
    assert ", 2 sent no request (--first-request-timeout)" in log.splitlines()[-1]


def test_64_one_byte_clients_cannot_keep_a_normal_client_out():
    # The first-request timeout is far off: only giving a slot can let the normal client in.
    with serve("--first-request-timeout", "30", quiet=False) as server:
        attackers = one_byte_clients(server, 64)
        try:
            time.sleep(0.3)  # the server has taken all 64
            latencies = []
            for _ in range(3):  # new connections, each served at once
                normal = pymodbus_tcp(server)
                try:
                    latencies.append(timed_read(normal))
                finally:
                    normal.close()
            gone = sum(closed_by_peer(sock) for sock in attackers)
        finally:
            for sock in attackers:
                sock.close()
        print(
            f"\n64 one-byte clients: normal client's worst reply {max(latencies) * 1000:.0f} ms; {gone} gave their slot"
        )
        assert max(latencies) < PROMPT
        assert gone >= 1  # the oldest of them made room
    log = server.log()
    assert "gave its slot to a newcomer: no request since it connected (--max-clients)" in log
    assert "gave their slot to a newcomer (--max-clients)" in log.splitlines()[-1]


def _reconnecting_attacker(server, count: int, stop: threading.Event, made: list[int]) -> None:
    """Keep ``count`` connections that send one byte each; reconnect each one the server closes."""
    socks: list[socket.socket | None] = [None] * count
    try:
        while not stop.is_set():
            for i, sock in enumerate(socks):
                if sock is not None and not closed_by_peer(sock):
                    continue
                if sock is not None:
                    sock.close()
                try:
                    sock = socket.create_connection((server.host, server.port), timeout=PROMPT)
                    sock.send(b"\x00")
                except OSError:
                    sock = None
                socks[i] = sock
                made[0] += 1
            select.select([], [], [], 0.005)
    finally:
        for sock in socks:
            if sock is not None:
                sock.close()


def test_a_reconnecting_attacker_cannot_keep_a_normal_client_out():
    cap = 16
    args = ("--max-clients", str(cap), "--first-request-timeout", "0.5")
    with serve(*args) as server:
        stop = threading.Event()
        made = [0]
        attacker = threading.Thread(
            target=_reconnecting_attacker, args=(server, cap + 8, stop, made), daemon=True
        )
        attacker.start()
        try:
            time.sleep(0.5)  # every slot is the attacker's, and it churns
            latencies = []
            steady = pymodbus_tcp(server)  # one client that stays, polling
            try:
                end = time.monotonic() + 3
                while time.monotonic() < end:
                    latencies.append(timed_read(steady))
                    fresh = pymodbus_tcp(server)  # and one that comes and goes
                    try:
                        latencies.append(timed_read(fresh))
                    finally:
                        fresh.close()
                    time.sleep(0.1)
            finally:
                steady.close()
        finally:
            stop.set()
            attacker.join(timeout=5)
        print(
            f"\nreconnecting attacker ({made[0]} connections): normal clients' worst reply"
            f" {max(latencies) * 1000:.0f} ms over {len(latencies)} reads"
        )
        assert made[0] > 2 * cap  # the attacker did reconnect
        assert max(latencies) < PROMPT


def test_a_busy_client_keeps_its_slot_and_used_ones_go_by_last_use():
    """Past the cap with no unused connection, the client longest without a request goes."""
    with serve("--max-clients", "2", quiet=False) as server:
        older = server.connect()
        newer = server.connect()
        try:
            for tid, sock in ((1, older), (2, newer)):
                sock.sendall(mbap(tid, 1, bytes.fromhex("0300070001")))
                assert sock.recv(100) == mbap(tid, 1, bytes.fromhex("03020007"))
            time.sleep(0.1)
            newer.sendall(mbap(3, 1, bytes.fromhex("0300070001")))  # older is now the least recently used
            assert newer.recv(100) == mbap(3, 1, bytes.fromhex("03020007"))
            with server.connect() as newcomer:
                newcomer.sendall(mbap(4, 1, bytes.fromhex("0300080001")))
                assert newcomer.recv(100) == mbap(4, 1, bytes.fromhex("03020008"))
            assert closed_by_peer(older, wait=PROMPT)
            assert not closed_by_peer(newer)
        finally:
            with contextlib.suppress(OSError):
                older.close()
            newer.close()
    assert "gave its slot to a newcomer: idle for" in server.log()
