"""``mbtool serve`` under abuse: idle and dripping clients, too many clients, garbage and
oversized frames, clients that never read their replies, and the default listen address.

Each server is a subprocess whose stdout goes to a file (not a pipe a busy test might not
drain, which would stall the server's log and look like the very blocking tested for).
The abuse comes from raw sockets and ptys; pymodbus's client, an independent
implementation, checks the server still answers, and how fast.  Memory is the server's
VmRSS from /proc.  Figures are printed (``pytest -s`` shows them).
"""

from __future__ import annotations

import contextlib
import os
import random
import select
import socket
import struct
import threading
import time

import pytest
from helpers.checks import assert_one_error_line, closed_by_peer
from helpers.frames import ascii_frame, crc16, mbap
from helpers.ptys import PtyPair
from helpers.run import run_cli
from helpers.served import PROMPT, pymodbus_tcp, serve, serving_line, start_serve, stop_serve, timed_read

from mbtool.device.model import MAX_FILES

pytestmark = pytest.mark.timeout(60)

MB = 1024 * 1024


# --- where it listens ---------------------------------------------------------------------


def _non_loopback_address() -> str | None:
    """An IPv4 address of this host other than loopback, if it has one."""
    candidates = []
    with contextlib.suppress(OSError):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # no packet is sent: this only picks a route
            candidates.append(probe.getsockname()[0])
    with contextlib.suppress(OSError):
        candidates += socket.gethostbyname_ex(socket.gethostname())[2]
    return next((a for a in candidates if not a.startswith("127.") and a != "0.0.0.0"), None)


def _reachable(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=PROMPT):
            return True
    except OSError:
        return False


def test_default_listen_address_is_loopback(tmp_path):
    # Without -p: 127.0.0.1:5020.  Another test run may hold 5020; then the refusal still
    # names the address it tried, which is what matters here.
    proc, log_path, err_path = start_serve([], tmp_path, quiet=True)
    try:
        line = serving_line(proc, log_path)
        if line is None:
            assert proc.wait(timeout=5) == 6, err_path.read_text()
            assert "cannot listen on 127.0.0.1:5020" in err_path.read_text()
        else:
            assert line.startswith("serving tcp://127.0.0.1:5020 "), line
            other = _non_loopback_address()
            if other:
                assert not _reachable(other, 5020), f"the default listener answers on {other}"
    finally:
        stop_serve(proc)
    assert "Traceback" not in err_path.read_text()

    other = _non_loopback_address()
    if other is None:
        pytest.skip("this host has no address but loopback to try from")
    # A loopback target is reachable on loopback only; an address the user names is used as is.
    with serve() as server:
        assert _reachable("127.0.0.1", server.port)
        assert not _reachable(other, server.port)
    with serve(target="tcp://0.0.0.0:0") as server:
        assert server.host == "0.0.0.0"
        assert _reachable(other, server.port)


# --- clients that hold a slot without using it ---------------------------------------------


@pytest.mark.parametrize("framer", ["tcp", "rtu"])
def test_idle_and_dripping_clients_are_closed_active_ones_kept(framer):
    idle_timeout = 1.0
    request = mbap(1, 1, bytes.fromhex("0300000001")) if framer == "tcp" else bytes.fromhex("010300000001")
    if framer == "rtu":
        request += crc16(request)
    else:
        # The header promises a 253-byte PDU: it never completes at one byte a turn.
        request = struct.pack(">HHHB", 1, 0, 254, 1) + b"\x10" * 253
    with serve("--framer", framer, "--idle-timeout", str(idle_timeout), quiet=False) as server:
        active = pymodbus_tcp(server, framer)
        try:
            silent = server.connect()
            drip = server.connect()
            opened = time.monotonic()
            closed_at: dict[str, float] = {}
            latencies = []
            sent = 0
            end = opened + 4 * idle_timeout + 6  # a deadline far past the expected closes
            # Until both are closed and the active client has outlived the timeout twice over.
            outlived = 2.5 * idle_timeout
            while time.monotonic() < end and (len(closed_at) < 2 or time.monotonic() - opened < outlived):
                if "drip" not in closed_at:
                    try:
                        drip.send(request[sent % len(request) : sent % len(request) + 1])
                        sent += 1
                    except OSError:
                        closed_at["drip"] = time.monotonic() - opened
                for name, sock in (("silent", silent), ("drip", drip)):
                    if name not in closed_at and closed_by_peer(sock):
                        closed_at[name] = time.monotonic() - opened
                latencies.append(timed_read(active))  # every 0.25 s: well inside the timeout
                time.sleep(0.25)
            elapsed = time.monotonic() - opened
            latencies.append(timed_read(active))
        finally:
            active.close()
            for sock in (silent, drip):
                sock.close()
        print(
            f"\n{framer}: closed after {closed_at} s (timeout {idle_timeout} s), drip sent {sent} bytes,"
            f" active client kept {elapsed:.1f} s, worst reply {max(latencies) * 1000:.0f} ms"
        )
        assert set(closed_at) == {"silent", "drip"}, closed_at
        for name, at in closed_at.items():
            assert idle_timeout * 0.9 <= at <= idle_timeout + 3, (name, at)
        assert sent >= 3  # the drip did send bytes while it waited to be closed
        assert elapsed > 2 * idle_timeout
        assert max(latencies) < PROMPT
    log = server.log()  # now the server has stopped and printed its summary
    assert log.count("idle timeout: nothing received for") == 1, log
    assert log.count("idle timeout: bytes but no whole request for") == 1, log
    if framer == "tcp":  # MBAP keeps the partial frame; RTU over TCP ends each byte on the pause
        assert "bytes of one buffered" in log
    assert ", 2 timed out (--idle-timeout)" in log.splitlines()[-1]


def test_connection_cap_refuses_newcomers_while_every_client_is_busy():
    # A newcomer past the cap takes an idle client's slot (tests/e2e/test_serve_guard.py); with
    # every client owed a reply (--delay) none is idle, and a newcomer is closed at once.
    cap, delay = 3, 3.0
    with serve(
        "--max-clients", str(cap), "--idle-timeout", "0", "--delay", str(delay), quiet=False
    ) as server:
        served = [server.connect() for _ in range(cap)]
        extra: list[socket.socket] = []
        try:
            for tid, sock in enumerate(served):
                sock.sendall(mbap(tid, 1, bytes.fromhex("0300070001")))
            t0 = time.monotonic()
            time.sleep(0.2)  # the server has read the requests: it owes every client a reply
            # A burst past the cap: each is closed at once, none waits for a timeout.
            for _ in range(40):
                sock = server.connect()
                with contextlib.suppress(OSError):  # it may be closed already
                    sock.send(mbap(9, 1, bytes.fromhex("0300000001")))
                extra.append(sock)
            refused = [closed_by_peer(sock, wait=PROMPT) for sock in extra]
            refused_in = time.monotonic() - t0
            assert all(refused), refused.count(False)
            assert refused_in < delay, "the replies were due before the burst was refused"
            # The busy clients never noticed: each gets its reply.
            for sock in served:
                sock.settimeout(delay + PROMPT)
            replies = [sock.recv(100) for sock in served]
            assert replies == [mbap(tid, 1, bytes.fromhex("03020007")) for tid in range(cap)]
        finally:
            for sock in served + extra:
                sock.close()
        print(f"\n40 connections past a cap of {cap} busy clients closed within {refused_in * 1000:.0f} ms")
    log = server.log()  # now the server has stopped and printed its summary
    assert log.count(f"refused: {cap} clients already connected and busy") >= 40
    assert "refused (--max-clients)" in log.splitlines()[-1]


# --- garbage and oversized frames ---------------------------------------------------------


def _flood(sock: socket.socket, chunks, seconds: float, sent: list[int]) -> None:
    """Send chunks until they run out or the deadline passes; never block past it."""
    end = time.monotonic() + seconds
    sock.settimeout(0.2)
    for chunk in chunks:
        view = memoryview(chunk)
        while view and time.monotonic() < end:
            try:
                n = sock.send(view)
            except TimeoutError:
                continue
            except OSError:
                return
            view = view[n:]
            sent[0] += n
        if time.monotonic() >= end:
            return


def _watch_flood(server, good, rss_before: int, sock, chunks, seconds: float, sent: list[int]):
    """Flood from a thread while another client reads: (its latencies, the server's peak RSS)."""
    thread = threading.Thread(target=_flood, args=(sock, chunks, seconds, sent), daemon=True)
    thread.start()
    latencies = []
    peak = rss_before
    while thread.is_alive():
        latencies.append(timed_read(good))
        peak = max(peak, server.rss_kb())
        time.sleep(0.05)
    thread.join(timeout=1)
    return latencies, peak


def _ascii_garbage(total: int):
    """Random bytes, runs of hex after ':' that never end (oversized frames), bad LRCs."""
    rng = random.Random(7)
    bad_lrc = ascii_frame(1, bytes.fromhex("0300000001"))[:-4] + b"00\r\n"
    made = 0
    while made < total:
        kind = made // 65536 % 3
        if kind == 0:
            chunk = rng.randbytes(65536)
        elif kind == 1:
            chunk = b":" + b"0123456789ABCDEF" * 4096  # 64 KiB of one frame with no end
        else:
            chunk = bad_lrc * (65536 // len(bad_lrc))
        made += len(chunk)
        yield chunk


@pytest.mark.parametrize(("framer", "total"), [("ascii", 8 * MB), ("rtu", 256 * 1024)])
def test_garbage_flood_keeps_memory_bounded_and_others_served(framer, total):
    # RTU resynchronises byte by byte (about 8 µs a byte today), so it gets less garbage;
    # ASCII gets far more than the memory bound, so a buffer that kept it would show.
    with serve("--framer", framer) as server:
        good = pymodbus_tcp(server, framer)
        flooder = server.connect()
        try:
            # The flooder's good request (register 8 of unit 1) and its reply, in the framing.
            if framer == "ascii":
                request, expected = (
                    ascii_frame(1, bytes.fromhex("0300080001")),
                    ascii_frame(1, bytes.fromhex("03020008")),
                )
            else:
                request = bytes.fromhex("010300080001") + crc16(bytes.fromhex("010300080001"))
                expected = bytes.fromhex("0103020008") + crc16(bytes.fromhex("0103020008"))
            # It asks once as a client would first: a flood that a loaded machine stretches past
            # serve's --first-request-timeout (5 s) must not close it for that.
            flooder.sendall(request)
            first = b""
            while expected not in first:
                first += flooder.recv(4096)
            for _ in range(20):  # warm up: first-use allocations are not growth
                timed_read(good)
            before = server.rss_kb()
            if framer == "ascii":
                chunks = _ascii_garbage(total)
            else:
                rng = random.Random(3)
                chunks = (rng.randbytes(65536) for _ in range(total // 65536))
            sent = [0]
            t0 = time.monotonic()
            latencies, peak = _watch_flood(server, good, before, flooder, chunks, 20.0, sent)
            flood_time = time.monotonic() - t0
            # The flooder's own stream resynchronises: after a pause, a good request is answered
            # once the server has chewed through the garbage the kernel still holds; the other
            # client is timed all along.
            time.sleep(0.3)
            flooder.sendall(request)
            got = b""
            end = time.monotonic() + 15
            while expected not in got and time.monotonic() < end:
                latencies.append(timed_read(good))
                peak = max(peak, server.rss_kb())
                ready, _, _ = select.select([flooder], [], [], 0.05)
                if ready:
                    got += flooder.recv(4096)
            chewed = time.monotonic() - t0
            after = server.rss_kb()
            latencies.append(timed_read(good))
        finally:
            good.close()
            flooder.close()
        print(
            f"\n{framer}: {sent[0] / MB:.1f} MB of garbage sent in {flood_time:.1f} s, resync reply"
            f" after {chewed:.1f} s; RSS {before} kB before,"
            f" peak {peak} kB, {after} kB after; other client's worst reply"
            f" {max(latencies) * 1000:.0f} ms over {len(latencies)} reads"
        )
        assert sent[0] >= total * 0.9 if framer == "ascii" else sent[0] == total
        assert expected in got, got[-200:]
        assert max(latencies) < PROMPT
        assert max(peak, after) - before < 4 * 1024, (before, peak, after)  # far less than the garbage


def test_bad_mbap_requests_on_many_connections():
    """Truncated, oversized, zero-length, wrong protocol id, garbage: each on its own
    connection, interleaved with a good client; the server answers what it can, hangs
    up on what cannot be resynchronised, and the good client never waits."""
    rng = random.Random(11)
    abuses = [
        b"\x00\x05\x00",  # a truncated header, then the client leaves
        mbap(2, 1, b"\x03\x00"),  # a truncated PDU in a whole frame: exception 03
        struct.pack(">HHHB", 3, 0, 2000, 1) + b"\x03" * 300,  # an oversized length
        struct.pack(">HHHB", 4, 0, 0, 1),  # length 0
        struct.pack(">HHHB", 5, 7, 6, 1) + bytes.fromhex("0300000001"),  # protocol id 7
        rng.randbytes(256 * 1024),  # garbage
        mbap(6, 1, b"\x41"),  # an unknown function code: exception 01
    ]
    with serve() as server:
        good = pymodbus_tcp(server)
        try:
            timed_read(good)
            before = server.rss_kb()
            latencies = []
            answers = {}
            for round_ in range(15):
                for index, data in enumerate(abuses):
                    with server.connect() as sock:
                        with contextlib.suppress(OSError):
                            sock.sendall(data)
                        if index in (1, 6):
                            answers[index] = sock.recv(100)
                latencies.append(timed_read(good, address=round_))
            after = server.rss_kb()
        finally:
            good.close()
        print(
            f"\n{15 * len(abuses)} bad connections: RSS {before} kB -> {after} kB;"
            f" good client's worst reply {max(latencies) * 1000:.0f} ms"
        )
        assert answers == {1: mbap(2, 1, b"\x83\x03"), 6: mbap(6, 1, b"\xc1\x01")}
        assert max(latencies) < PROMPT
        assert after - before < 8 * 1024


@pytest.mark.parametrize("framer", ["rtu", "ascii"])
def test_bad_frames_on_a_serial_line(framer):
    """Truncated, oversized and garbage frames on a pty; then pymodbus's serial client is answered."""
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    rng = random.Random(5)
    if framer == "rtu":
        request = bytes.fromhex("011000000002040001000200")  # FC16, promised 4 bytes
        abuse = [
            request[:5],  # truncated
            bytes.fromhex("01100000007DFA") + bytes(250) + b"\x00" * 60,  # past 256 bytes, bad CRC
            rng.randbytes(48 * 1024),
        ]
    else:
        abuse = [
            b":0103000",  # truncated, never ended
            b":" + b"01" * 600 + b"\r\n",  # past 513 characters
            b":0103000000010000\r\n",  # bad LRC
            rng.randbytes(96 * 1024),
            b"\r\n:" + b"AB" * 4000,  # hex with no end
        ]
    pair = PtyPair()
    try:
        with serve("--framer", framer, "--parity", "N", target=pair.device_path) as server:
            fd = os.open(pair.mbtool_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            try:
                end = time.monotonic() + 20
                for data in abuse:
                    view = memoryview(data)
                    while view and time.monotonic() < end:
                        _, writable, _ = select.select([], [fd], [], 0.1)
                        if writable:
                            with contextlib.suppress(BlockingIOError):
                                view = view[os.write(fd, view) :]
                    time.sleep(0.1)  # a pause ends a frame on a serial line
                assert time.monotonic() < end, "the server stopped reading the line"
                # ASCII gives up on a frame after 1 s without characters (spec §2).
                time.sleep(1.2 if framer == "ascii" else 0.3)
            finally:
                os.close(fd)
            kind = FramerType.RTU if framer == "rtu" else FramerType.ASCII
            client = ModbusSerialClient(
                pair.mbtool_path, framer=kind, baudrate=19200, timeout=PROMPT, retries=0
            )
            assert client.connect()
            try:
                t0 = time.monotonic()
                assert client.read_holding_registers(9, count=2).registers == [9, 10]
                elapsed = time.monotonic() - t0
                assert not client.write_registers(20, [1, 2]).isError()
                errors = client.diag_read_bus_comm_error_count().message
            finally:
                client.close()
            print(
                f"\n{framer} on a pty: answered {elapsed * 1000:.0f} ms after the abuse;"
                f" bus error counter {errors}"
            )
            assert elapsed < PROMPT
            assert (errors[0] if isinstance(errors, list | tuple) else errors) >= 1
            assert server.alive()
    finally:
        pair.close()


# --- clients that do not read -------------------------------------------------------------


def test_pipelined_requests_are_all_answered_in_order():
    """The reply queue behind the non-blocking sends loses and reorders nothing."""
    with serve() as server:
        with server.connect() as sock:
            count = 3000
            requests = b"".join(mbap(tid, 1, struct.pack(">BHH", 3, tid % 100, 1)) for tid in range(count))
            sender = threading.Thread(target=_flood, args=(sock, [requests], 20.0, [0]), daemon=True)
            sender.start()
            expected = b"".join(mbap(tid, 1, struct.pack(">BBH", 3, 2, tid % 100)) for tid in range(count))
            got = bytearray()
            end = time.monotonic() + 20
            while len(got) < len(expected) and time.monotonic() < end:
                with contextlib.suppress(TimeoutError):
                    got += sock.recv(65536)
            sender.join(timeout=1)
    assert bytes(got) == expected


def test_client_that_never_reads_blocks_nobody_and_is_closed():
    idle_timeout = 1.0
    with serve("--idle-timeout", str(idle_timeout)) as server:
        good = pymodbus_tcp(server)
        slow = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fill up soon
        slow.settimeout(PROMPT)
        slow.connect((server.host, server.port))
        try:
            for _ in range(20):
                timed_read(good)
            before = server.rss_kb()
            # Requests for 125 registers: 259-byte replies for 12-byte requests.
            request = mbap(1, 1, struct.pack(">BHH", 3, 0, 125))
            sent = [0]
            chunks = (request * 1000 for _ in range(1000))
            latencies, peak = _watch_flood(server, good, before, slow, chunks, 1.5, sent)
            # The server owes it thousands of replies and it takes none: after the idle
            # timeout it is closed.  Reading first would be taking replies, so wait, then
            # drain: a closed socket ends in EOF or a reset, an open one never ends.
            latencies.append(timed_read(good))
            time.sleep(idle_timeout + 2)
            closed = closed_by_peer(slow, wait=8)
            after = server.rss_kb()
        finally:
            good.close()
            slow.close()
        requests_sent = sent[0] // len(request)
        print(
            f"\nslow consumer: {requests_sent} requests accepted before its sends stalled"
            f" ({requests_sent * 259 / MB:.1f} MB of replies owed); RSS {before} kB before, peak {peak} kB,"
            f" {after} kB after;"
            f" other client's worst reply {max(latencies) * 1000:.0f} ms"
        )
        assert closed
        assert max(latencies) < PROMPT
        # Back-pressure: the kernel's buffers, not the server's memory, hold what it would not take.
        assert max(peak, after) - before < 8 * 1024, (before, peak, after)


# --- what a client or a data file can make the server hold (issue 29 item 1) ---------------


def _mbap_replies(sock: socket.socket, count: int) -> list[bytes]:
    """``count`` whole MBAP replies' PDUs."""
    pdus, data = [], b""
    end = time.monotonic() + 10 * PROMPT
    while len(pdus) < count and time.monotonic() < end:
        data += sock.recv(65536)
        while len(data) >= 6 and len(data) >= 6 + struct.unpack_from(">H", data, 4)[0]:
            size = 6 + struct.unpack_from(">H", data, 4)[0]
            pdus.append(data[7:size])
            data = data[size:]
    return pdus


def test_writes_to_thousands_of_files_get_exception_02_past_the_bound():
    files = 4000
    with serve() as server:
        good = pymodbus_tcp(server)
        hostile = server.connect()
        try:
            timed_read(good)
            before = server.rss_kb()
            answers = []
            for first in range(1, files + 1, 100):
                numbers = range(first, min(files, first + 99) + 1)
                hostile.sendall(
                    b"".join(mbap(n, 1, struct.pack(">BBBHHHH", 0x15, 9, 6, n, 0, 1, 7)) for n in numbers)
                )
                answers += _mbap_replies(hostile, len(numbers))
            after = server.rss_kb()
            latency = timed_read(good)
        finally:
            good.close()
            hostile.close()
        print(f"\n{files} FC21 writes to distinct files: RSS {before} kB -> {after} kB")
        assert len(answers) == files
        assert answers[MAX_FILES] == b"\x95\x02"
        assert answers.count(b"\x95\x02") == files - MAX_FILES
        assert after - before < 4 * 1024, (before, after)  # 4000 files were 80 MB
        assert latency < PROMPT


def test_replies_held_back_by_delay_count_towards_the_output_limit():
    # --delay holds each reply for 30 s: a client that pipelines requests made the server hold
    # every reply it owed, 150 MB in 8 s.
    with serve("--delay", "30", "--idle-timeout", "0") as server:
        flooder = server.connect()
        try:
            before = server.rss_kb()
            request = mbap(1, 1, struct.pack(">BHH", 3, 0, 125))  # 259-byte replies
            sent = [0]
            _flood(flooder, (request * 1000 for _ in range(10_000)), 4.0, sent)
            after = server.rss_kb()
        finally:
            flooder.close()
        print(f"\n{sent[0] // len(request)} requests sent at --delay 30: RSS {before} kB -> {after} kB")
        assert after - before < 8 * 1024, (before, after)


def test_a_data_file_with_more_files_than_a_unit_holds_is_refused(tmp_path):
    path = tmp_path / "files.toml"
    path.write_text("".join(f"[files.{n}]\n0 = 1\n" for n in range(1, MAX_FILES + 2)))
    line = assert_one_error_line(run_cli("serve", "-q", "-p", "tcp://127.0.0.1:0", "--data", str(path)), 2)
    assert f"{MAX_FILES + 1} files: a unit holds at most {MAX_FILES}" in line
    help_text = " ".join(run_cli("serve", "--help").stdout.split())
    assert f"at most {MAX_FILES} files (FC 20/21)" in help_text  # the bound is stated
