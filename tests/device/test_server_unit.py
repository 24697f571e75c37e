"""The server behind serve and bridge (mbtool.device.server and what it runs), in-process.

The replies and the I/O layer's faults (``Responder``) are checked event by event; the TCP
server runs in a thread on a loopback port, the serial one on a line made of a loopback
socket (pyserial's socket://), with the test as the master; a gateway's forwarder is stood
in for by answerers of the test's own.
"""

from __future__ import annotations

import contextlib
import random
import select
import socket
import threading
import time

import pytest
from helpers.checks import closed_by_peer, wait_until
from helpers.frames import ascii_frame, crc16, lrc, mbap, rtu

from mbtool.codec.framing import Frame, Rejected, device_framer
from mbtool.device.device import Device
from mbtool.device.model import demo_model
from mbtool.device.server import Server, parse_target
from mbtool.device.serving import IoFaults, Responder, Stats, corrupt_checksum, deviate
from mbtool.device.tcp_server import BUS_HALF_LIFE, _Client, _Turns
from mbtool.errors import ConnectionFailed, UsageError
from mbtool.link import IN_PROCESS

pytestmark = pytest.mark.timeout(60)

PROMPT = 5.0  # generous: other test runs share the cores
QUIET = 0.3  # how long a reply that must not come is waited for
READ = bytes.fromhex("03 0000 0002")  # FC03 two registers from 0: the demo data holds 0, 1
READ_REPLY = bytes.fromhex("03 04 0000 0001")


def H(text: str) -> bytes:
    return bytes.fromhex(text)


class Log:
    """The server's log callback: every (direction, peer, data, note) it was given."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, bytes, str]] = []

    def __call__(self, direction: str, peer: str, data: bytes, note: str) -> None:
        self.lines.append((direction, peer, data, note))

    def notes(self, direction: str) -> list[str]:
        return [note for d, _, _, note in self.lines if d == direction]


# --- the replies: the device's answer with the I/O layer's faults (Responder) -----------------


def responder(faults: IoFaults | None = None, device: Device | None = None) -> tuple[Responder, Stats, Log]:
    stats, log = Stats(), Log()
    device = device or Device(demo_model(), frozenset({1}))
    return Responder(device, faults or IoFaults(), stats, random.Random(1), log), stats, log


def event(framer_name: str, unit: int, pdu: bytes, transaction_id: int = 7):
    """A request as the server's framer hands it over, and that framer."""
    framer = device_framer(framer_name)
    framer.feed(framer.build(unit, pdu, transaction_id))
    return framer.next_event() or framer.silence(), framer


def test_a_request_gets_the_device_s_reply_and_both_are_counted_and_logged():
    answer, stats, log = responder()
    request, framer = event("tcp", 1, READ)
    assert answer.answer(request, framer, "peer") == mbap(7, 1, READ_REPLY)
    assert (stats.requests, stats.replies) == (1, 1)
    assert [d for d, *_ in log.lines] == ["RX", "TX"]
    assert [(d, adu) for _, d, _, adu, _ in stats.frames] == [
        ("RX", request.adu),
        ("TX", mbap(7, 1, READ_REPLY)),
    ]


def test_bytes_that_make_no_frame_are_logged_and_counted_by_the_device():
    device = Device(demo_model(), frozenset({1}))
    answer, stats, log = responder(device=device)
    framer = device_framer("rtu")
    framer.feed(rtu(b"\x01" + READ)[:-1] + b"\x00")  # a bad CRC
    rejected = framer.next_event() or framer.silence()
    assert isinstance(rejected, Rejected)
    assert answer.answer(rejected, framer, "/dev/ttyS0") is None
    assert stats.requests == 0
    assert [d for d, *_ in log.lines] == ["bad"]
    assert device.bus["bus_comm_errors"] == 1  # FC08 sub 0C (spec §4)


@pytest.mark.parametrize(
    "unit, pdu, why",
    [
        (0, H("06 0001 0003"), "broadcast: applied, never answered"),
        (5, READ, "unit 5 is not served: ignored"),
        (1, H("08 0004 0000"), "listen-only mode: no reply"),
    ],
)
def test_a_request_left_unanswered_says_why(unit, pdu, why):
    answer, stats, log = responder()
    request, framer = event("rtu", unit, pdu)
    assert answer.answer(request, framer, "/dev/ttyS0") is None
    assert log.lines[-1] == ("--", "/dev/ttyS0", b"", why)
    assert (stats.requests, stats.replies) == (1, 0)


def test_drop_loses_the_reply_and_says_so():
    answer, stats, log = responder(IoFaults(drop=1.0))
    request, framer = event("tcp", 1, READ)
    assert answer.answer(request, framer, "peer") is None
    assert (stats.dropped, stats.replies) == (1, 0)
    assert log.lines[-1] == ("drop", "peer", mbap(7, 1, READ_REPLY), "reply dropped (--drop)")


def test_drop_spares_some_replies_as_its_fraction_and_seed_choose():
    answer, stats, _ = responder(IoFaults(drop=0.5))
    request, framer = event("tcp", 1, READ)
    replies = [answer.answer(request, framer, "peer") for _ in range(200)]
    assert 0 < stats.dropped < 200 and stats.replies == 200 - stats.dropped
    again, _, _ = responder(IoFaults(drop=0.5))  # the same seed drops the same replies
    assert [again.answer(request, framer, "peer") for _ in range(200)] == replies


def test_corrupt_makes_an_rtu_reply_s_crc_wrong_and_nothing_else():
    answer, stats, log = responder(IoFaults(corrupt=1.0))
    request, framer = event("rtu", 1, READ)
    reply = answer.answer(request, framer, "/dev/ttyS0")
    good = rtu(b"\x01" + READ_REPLY)
    assert reply[:-2] == good[:-2] and reply[-2:] != crc16(reply[:-2])
    assert stats.corrupted == 1
    assert log.lines[-1][3] == "checksum corrupted (--corrupt)"


def test_corrupt_makes_an_ascii_reply_s_lrc_wrong_and_keeps_it_hex():
    good = ascii_frame(1, READ_REPLY)
    bad = corrupt_checksum(good, "ascii")
    assert bad[:-4] == good[:-4] and bad[-2:] == b"\r\n"
    assert int(bad[-4:-2], 16) != lrc(bytes.fromhex(bad[1:-4].decode()))


def test_corrupt_leaves_an_mbap_reply_as_it_is():
    assert corrupt_checksum(mbap(7, 1, READ_REPLY), "tcp") == mbap(7, 1, READ_REPLY)


def test_pad_byte_count_off_and_reply_unit_bend_a_tcp_reply_and_keep_its_mbap_length_true():
    reply = mbap(7, 1, READ_REPLY)
    assert deviate(reply, IoFaults(pad=2)) == mbap(7, 1, READ_REPLY + b"\x00\x00")
    assert deviate(reply, IoFaults(byte_count_off=1)) == mbap(7, 1, H("03 05 0000 0001"))
    assert deviate(reply, IoFaults(reply_unit=9)) == mbap(7, 9, READ_REPLY)
    # Only the byte count of FC 01-04 replies is bent.
    assert deviate(mbap(7, 1, H("06 0001 0003")), IoFaults(byte_count_off=1)) == mbap(7, 1, H("06 0001 0003"))


def test_tcp_deviations_leave_serial_replies_alone():
    answer, _, _ = responder(IoFaults(pad=2, byte_count_off=1, reply_unit=9))
    request, framer = event("rtu", 1, READ)
    assert answer.answer(request, framer, "/dev/ttyS0") == rtu(b"\x01" + READ_REPLY)
    request, framer = event("tcp", 1, READ)
    assert answer.answer(request, framer, "peer") == mbap(7, 9, H("03 05 0000 0001 0000"))


def test_the_in_process_device_is_no_place_to_serve(monkeypatch):
    monkeypatch.setitem(IN_PROCESS, "sim", object)
    with pytest.raises(UsageError, match="in-process device"):
        parse_target("sim://")
    assert parse_target("tcp://127.0.0.1:0").port == 0  # port 0: any free port


# --- TCP ---------------------------------------------------------------------------------------


def tcp_server(framer: str = "tcp", device: Device | None = None, **options) -> Server:
    device = device or Device(demo_model(), frozenset({1}))
    return Server(device, parse_target("tcp://127.0.0.1:0"), framer, **options)


@contextlib.contextmanager
def running(server: Server):
    """The server open and running in a thread; what run() raised, if anything, in the list."""
    server.open()
    raised: list[BaseException] = []

    def run() -> None:
        try:
            server.run()
        except BaseException as error:
            raised.append(error)

    thread = threading.Thread(target=run, name="server-under-test", daemon=True)
    thread.start()
    try:
        yield raised
    finally:
        server.stop()
        thread.join(PROMPT)
        assert not thread.is_alive(), "the server did not stop"


def connect(server: Server) -> socket.socket:
    host, _, port = server.stats.listening.removeprefix("tcp://").rpartition(":")
    sock = socket.create_connection((host, int(port)), timeout=PROMPT)
    sock.settimeout(PROMPT)
    return sock


def receive(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            break
        data += chunk
    return data


def nothing_comes(sock: socket.socket, wait: float = QUIET) -> bool:
    ready, _, _ = select.select([sock], [], [], wait)
    return not ready


def test_tcp_answers_with_the_request_s_transaction_id():
    server = tcp_server()
    with running(server), connect(server) as sock:
        assert server.stats.listening.startswith("tcp://127.0.0.1:")
        sock.sendall(mbap(0x1234, 1, READ))
        assert receive(sock, 13) == mbap(0x1234, 1, READ_REPLY)
        sock.sendall(mbap(1, 1, READ) + mbap(2, 1, READ))  # two in one segment: both answered
        assert receive(sock, 26) == mbap(1, 1, READ_REPLY) + mbap(2, 1, READ_REPLY)


def test_rtu_over_tcp_ends_a_frame_of_unknown_length_at_a_pause():
    server = tcp_server("rtu")
    with running(server), connect(server) as sock:
        sock.sendall(rtu(b"\x01" + READ))
        assert receive(sock, 9) == rtu(b"\x01" + READ_REPLY)
        sock.sendall(rtu(H("01 41 0102")))  # a function code no framer can size
        assert receive(sock, 5) == rtu(H("01 C1 01"))


def test_bytes_that_are_not_mbap_close_that_client_only():
    log = Log()
    server = tcp_server(log=log)
    with running(server), connect(server) as bad, connect(server) as good:
        bad.sendall(b"\x00\x01\x12\x34\x00\x06\x01" + READ)  # protocol id 0x1234
        assert closed_by_peer(bad, PROMPT)
        good.sendall(mbap(3, 1, READ))
        assert receive(good, 13) == mbap(3, 1, READ_REPLY)
    assert any(note.startswith("not Modbus TCP") for note in log.notes("close"))


def test_a_client_that_sends_no_request_is_closed_at_the_first_request_timeout():
    server = tcp_server(first_request_timeout=0.3)
    with running(server), connect(server) as sock:
        sock.sendall(mbap(1, 1, READ)[:5])  # the start of a request, never finished
        assert closed_by_peer(sock, PROMPT)
        assert server.stats.unused == 1
    assert "5 bytes of one buffered" in server.stats.frames[-1][4]


def test_a_client_idle_after_its_request_is_closed_at_the_idle_timeout():
    server = tcp_server(idle_timeout=0.3, first_request_timeout=None)
    with running(server), connect(server) as sock:
        sock.sendall(mbap(1, 1, READ))
        assert receive(sock, 13) == mbap(1, 1, READ_REPLY)
        assert closed_by_peer(sock, PROMPT)
        assert server.stats.expired == 1
    assert server.stats.frames[-1][4].startswith("idle timeout: nothing received for")


def test_a_newcomer_past_max_clients_takes_the_slot_of_a_client_that_sent_nothing():
    server = tcp_server(max_clients=1)
    with running(server), connect(server) as first:
        assert wait_until(lambda: server.stats.clients == 1, PROMPT)
        with connect(server) as newcomer:
            assert closed_by_peer(first, PROMPT)
            newcomer.sendall(mbap(1, 1, READ))
            assert receive(newcomer, 13) == mbap(1, 1, READ_REPLY)
        assert (server.stats.evicted, server.stats.refused) == (1, 0)
    assert ("close", "gave its slot to a newcomer: no request since it connected") in [
        (direction, note) for _, direction, _, _, note in server.stats.frames
    ]


def test_a_client_that_sent_nothing_gives_its_slot_before_one_that_used_it():
    server = tcp_server(max_clients=2)
    with running(server), connect(server) as used:
        used.sendall(mbap(1, 1, READ))
        assert receive(used, 13) == mbap(1, 1, READ_REPLY)
        with connect(server) as silent:  # idle for less time than the first, but never asked
            assert wait_until(lambda: server.stats.clients == 2, PROMPT)
            with connect(server) as newcomer:
                assert closed_by_peer(silent, PROMPT)
                newcomer.sendall(mbap(2, 1, READ))
                assert receive(newcomer, 13) == mbap(2, 1, READ_REPLY)
        used.sendall(mbap(3, 1, READ))
        assert receive(used, 13) == mbap(3, 1, READ_REPLY)


def test_a_newcomer_past_max_clients_is_refused_while_every_client_is_owed_a_reply():
    server = tcp_server(max_clients=1, faults=IoFaults(delay=1.0))
    with running(server), connect(server) as first:
        first.sendall(mbap(1, 1, READ))  # its reply is held back: it is busy
        assert wait_until(lambda: server.stats.requests == 1, PROMPT)
        with connect(server) as newcomer:
            assert closed_by_peer(newcomer, PROMPT)
        assert wait_until(lambda: server.stats.refused == 1, PROMPT)  # counted once it is closed
        assert receive(first, 13) == mbap(1, 1, READ_REPLY)  # the client served never noticed


def test_delay_holds_each_reply_back():
    server = tcp_server(faults=IoFaults(delay=0.3))
    with running(server), connect(server) as sock:
        sent = time.monotonic()
        sock.sendall(mbap(1, 1, READ))
        assert receive(sock, 13) == mbap(1, 1, READ_REPLY)
        assert time.monotonic() - sent >= 0.3


@pytest.mark.parametrize(
    "faults, answered, why",
    [
        (IoFaults(settle=60.0), 0, "request too soon after connecting: dropped (--settle)"),
        (IoFaults(min_gap=60.0), 1, "request too soon after the last reply: dropped (--min-gap)"),
        (
            IoFaults(connection_requests=1),
            1,
            "past this connection's requests: dropped (--connection-requests)",
        ),
    ],
)
def test_a_request_a_picky_device_would_drop_gets_no_reply(faults, answered, why):
    log = Log()
    server = tcp_server(faults=faults, log=log)
    with running(server), connect(server) as sock:
        for tid in range(1, answered + 1):
            sock.sendall(mbap(tid, 1, READ))
            assert receive(sock, 13) == mbap(tid, 1, READ_REPLY)
        sock.sendall(mbap(9, 1, READ))
        assert nothing_comes(sock)
        assert server.stats.dropped == 1
    assert log.notes("drop") == [why]


def test_stop_ends_run_and_closes_every_client():
    log = Log()
    server = tcp_server(log=log)
    with running(server) as raised, connect(server) as sock:
        assert wait_until(lambda: server.stats.clients == 1, PROMPT)
        server.stop()
        assert closed_by_peer(sock, PROMPT)
    assert raised == []
    assert "server stopped" in log.notes("close")


def test_a_port_in_use_cannot_be_served_on():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        server = Server(Device(), parse_target(f"tcp://127.0.0.1:{port}"), "tcp")
        with pytest.raises(ConnectionFailed, match=f"cannot listen on 127.0.0.1:{port}"):
            server.open()


# --- queued answers: a bus behind the server (bridge) -------------------------------------------


class Gate:
    """An answerer that holds each request until let through, as a bus takes its time."""

    def __init__(self) -> None:
        self.asked: list[bytes] = []
        self.go = threading.Semaphore(0)

    def answer(self, event, framer, peer):
        self.asked.append(event.pdu)
        assert self.go.acquire(timeout=PROMPT), "the test never let the request through"
        return framer.build(event.unit, b"\x03\x02" + event.pdu[-2:], event.transaction_id or 0)


def test_queued_answers_take_their_time_while_the_loop_goes_on_serving():
    gate = Gate()
    server = tcp_server(answerer=gate, queued=True)
    with running(server), connect(server) as first:
        first.sendall(mbap(1, 1, H("03 0000 0001")))
        assert wait_until(lambda: len(gate.asked) == 1, PROMPT)
        with connect(server) as second:  # accepted while the first's answer is under way
            assert wait_until(lambda: server.stats.connections == 2, PROMPT)
            second.sendall(mbap(2, 1, H("03 0000 0002")))
            assert nothing_comes(first)
            gate.go.release()
            assert receive(first, 11) == mbap(1, 1, H("03 02 0001"))
            gate.go.release()
            assert receive(second, 11) == mbap(2, 1, H("03 02 0002"))
    assert gate.asked == [H("03 0000 0001"), H("03 0000 0002")]


def test_a_client_gone_while_its_request_waits_never_reaches_the_bus():
    gate = Gate()
    server = tcp_server(answerer=gate, queued=True)
    with running(server), connect(server) as first:
        first.sendall(mbap(1, 1, H("03 0000 0001")))
        assert wait_until(lambda: len(gate.asked) == 1, PROMPT)
        with connect(server) as gone:
            gone.sendall(mbap(2, 1, H("03 0000 0002")))
            assert wait_until(lambda: server.stats.requests == 0 and server.stats.connections == 2, PROMPT)
        assert wait_until(lambda: server.stats.clients == 1, PROMPT)  # its leaving was seen
        gate.go.release()
        assert receive(first, 11) == mbap(1, 1, H("03 02 0001"))
        first.sendall(mbap(3, 1, H("03 0000 0003")))
        gate.go.release()
        assert receive(first, 11) == mbap(3, 1, H("03 02 0003"))
    assert gate.asked == [H("03 0000 0001"), H("03 0000 0003")]


def test_a_failing_answerer_ends_run_with_its_error():
    class Broken:
        def answer(self, event, framer, peer):
            raise ZeroDivisionError("a bug in the answerer")

    server = tcp_server(answerer=Broken(), queued=True)
    with running(server) as raised, connect(server) as sock:
        sock.sendall(mbap(1, 1, READ))
        assert wait_until(lambda: raised, PROMPT)
    assert isinstance(raised[0], ZeroDivisionError)


def waiting_client(name: str) -> _Client:
    return _Client(None, name, device_framer("tcp"))


def test_the_next_turn_on_the_bus_is_the_client_s_with_the_least_bus_time_lately():
    turns = _Turns()
    busy, fresh, other = waiting_client("busy"), waiting_client("fresh"), waiting_client("other")
    busy.use_bus(2.0)
    request = Frame(1, READ, mbap(1, 1, READ), 1)
    turns.put(busy, request)
    turns.put(fresh, request)
    turns.put(other, request)
    assert [turns.next()[0].peer for _ in range(3)] == ["fresh", "other", "busy"]  # equals: who came first
    turns.close()
    assert turns.next() is None


def test_bus_time_counts_half_after_each_half_life():
    client = waiting_client("peer")
    client.use_bus(4.0)
    assert client.bus_time(client.bus_at + BUS_HALF_LIFE) == pytest.approx(2.0)
    assert client.bus_time(client.bus_at + 2 * BUS_HALF_LIFE) == pytest.approx(1.0)


# --- serial: a line made of a loopback socket ---------------------------------------------------


@contextlib.contextmanager
def serial_server(framer: str = "rtu", device: Device | None = None, **options):
    """A server on socket://127.0.0.1:PORT as its serial line (pyserial's url), running; the
    test's end of the line, what run() raised, and the server."""
    with socket.create_server(("127.0.0.1", 0)) as line:
        target = parse_target(f"socket://127.0.0.1:{line.getsockname()[1]}")
        server = Server(device or Device(demo_model(), frozenset({1})), target, framer, **options)
        with running(server) as raised:
            master, _ = line.accept()
            master.settimeout(PROMPT)
            with master:
                yield master, raised, server


def test_the_serial_line_answers_an_rtu_request():
    with serial_server() as (master, _, server):
        assert server.stats.listening.startswith("socket://127.0.0.1:")
        master.sendall(rtu(b"\x01" + READ))
        assert receive(master, 9) == rtu(b"\x01" + READ_REPLY)
        master.sendall(rtu(b"\x02" + READ))  # another slave's: silence
        assert nothing_comes(master)


def test_the_serial_line_answers_an_ascii_request():
    with serial_server("ascii") as (master, _, _):
        master.sendall(ascii_frame(1, READ))
        reply = ascii_frame(1, READ_REPLY)
        assert receive(master, len(reply)) == reply


def test_a_frame_with_a_bad_crc_gets_no_reply_and_counts_a_comm_error():
    device = Device(demo_model(), frozenset({1}))
    with serial_server(device=device) as (master, _, _):
        master.sendall(rtu(b"\x01" + READ)[:-1] + b"\x00")
        assert nothing_comes(master)
        assert wait_until(lambda: device.bus["bus_comm_errors"] == 1, PROMPT)


def test_requests_past_the_replies_delay_holds_back_are_dropped():
    log = Log()
    big = H("03 0000 007D")  # 125 registers: 255-byte replies
    with serial_server(faults=IoFaults(delay=60.0), log=log) as (master, _, server):
        master.sendall(rtu(b"\x01" + big) * 300)  # 300 replies would hold 76 KB
        assert wait_until(lambda: server.stats.dropped, PROMPT)
        assert nothing_comes(master)
    assert log.notes("drop")[0] == "request dropped: replies held back by --delay fill the output limit"


def test_the_line_going_away_ends_run_with_connection_failed():
    with serial_server() as (master, raised, _):
        master.close()
        assert wait_until(lambda: raised, PROMPT)
    assert isinstance(raised[0], ConnectionFailed)
    assert str(raised[0]).startswith("lost the serial line")
