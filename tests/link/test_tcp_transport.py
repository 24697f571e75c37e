"""The Modbus TCP transport against a real loopback socket: every wait ends on time.

Reads of 50 ms or more are timed by the kernel (SO_RCVTIMEO on a blocking socket, one
system call a read); shorter ones by select.  Writes to a peer that stopped reading end
after WRITE_TIMEOUT.
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers.checks import in_fresh_interpreter, unspecialized

from mbtool.errors import ConnectionFailed
from mbtool.link import base, transport
from mbtool.link.transport import ConnectionClosed, TcpTransport

pytestmark = pytest.mark.timeout(30)

# How late a loaded machine (other runs on the cores) may wake a thread whose wait has ended: a
# read's own timeout is kept to this margin, far less than the timeout it would have kept
# otherwise (the longer one before it, or the connection's).
LATE = 0.5


@pytest.fixture
def link():
    """A connected (transport, server-side socket) pair."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        host, port = listener.getsockname()
        tcp = TcpTransport(host, port, timeout=2)
        peer, _ = listener.accept()
    yield tcp, peer
    tcp.close()
    peer.close()


@pytest.mark.parametrize("timeout", [0.0, 0.02, 0.3, 1.0])
def test_a_read_with_nothing_coming_ends_at_its_timeout(link, timeout):
    tcp, _ = link
    start = time.monotonic()
    assert tcp.read(timeout) == b""
    assert timeout <= time.monotonic() - start + 0.001 < timeout + LATE


def test_a_shorter_timeout_after_a_longer_one_is_kept(link):
    """The socket's timeout is set again when a read's time left changes by more than slack."""
    tcp, _ = link
    assert tcp.read(1.0) == b""
    start = time.monotonic()
    assert tcp.read(0.2) == b""
    assert 0.2 <= time.monotonic() - start + 0.001 < 0.2 + LATE  # not the 1 s before it


def test_a_read_returns_as_soon_as_bytes_arrive(link):
    tcp, peer = link
    threading.Timer(0.05, peer.sendall, [b"\x00\x01reply"]).start()
    start = time.monotonic()
    assert tcp.read(5.0) == b"\x00\x01reply"
    assert time.monotonic() - start < 0.05 + LATE  # not the 5 s


def test_the_peer_hanging_up_is_connection_closed(link):
    tcp, peer = link
    peer.close()
    with pytest.raises(ConnectionClosed, match="closed the connection"):
        tcp.read(1.0)


def test_stale_bytes_are_discarded_without_waiting(link, monkeypatch):
    """Every wait the drain makes is one of no time (select's timeout, the system call's own
    word for it), not a wall-clock bound a loaded machine would break."""
    tcp, peer = link
    peer.sendall(b"stale reply")
    time.sleep(0.05)
    waits: list[float] = []

    def select(readers, writers, errors, timeout=None):
        waits.append(timeout)
        return real_select(readers, writers, errors, timeout)

    real_select = transport.select.select
    monkeypatch.setattr(transport.select, "select", select)
    start = time.monotonic()
    assert tcp.discard_input() == b"stale reply"
    assert tcp.discard_input() == b""
    assert waits and all(wait == 0 for wait in waits), waits
    assert time.monotonic() - start < LATE


def test_a_peer_that_stops_reading_fails_the_write_after_the_write_timeout(monkeypatch):
    monkeypatch.setattr(transport, "WRITE_TIMEOUT", 0.3)
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        tcp = TcpTransport(*listener.getsockname(), timeout=2)
        peer, _ = listener.accept()  # and never reads
        try:
            chunk = bytes(65536)
            start = time.monotonic()
            with pytest.raises(ConnectionFailed, match="has not read for 0.3 s"):
                while time.monotonic() - start < 20:
                    tcp.write(chunk)
            assert time.monotonic() - start < 10
        finally:
            tcp.close()
            peer.close()


# --- framing mix-ups named after silence, on any port (issue 12.17) -------------------------


@pytest.mark.parametrize("hang_up", [False, True], ids=["silent", "hangs-up"])
def test_socket_url_to_a_silent_peer_says_tcp_may_be_meant(hang_up):
    """A Modbus TCP device ignores RTU frames or hangs up on them, on whatever port it
    listens: the error says what is probably wrong."""
    from mbtool.codec.data_access import ReadHoldingRegisters
    from mbtool.codec.rtu import RtuFramer
    from mbtool.errors import NoResponse
    from mbtool.link.client import Client
    from mbtool.link.transport import SerialSettings, SerialTransport

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        link = SerialTransport(f"socket://127.0.0.1:{port}", SerialSettings())
        peer, _ = listener.accept()
        try:
            if hang_up:
                peer.close()
            client = Client(link, RtuFramer(), timeout=0.3)
            with pytest.raises(
                NoResponse, match=r"socket:// sends RTU or ASCII frames; for a Modbus TCP device use tcp://"
            ):
                client.execute(1, ReadHoldingRegisters(0, 1))
        finally:
            link.close()
            peer.close()


@pytest.mark.parametrize(
    "framer, hint",
    [
        # Silence over Modbus TCP is a plain timeout: the gateway hint needs RTU bytes to come
        # back (test_e2e_exit_codes: an RTU frame where MBAP was expected; issue 28).
        (None, None),
        ("rtu", "--framer rtu sends serial frames; for a Modbus TCP device leave --framer out"),
    ],
)
def test_tcp_url_to_a_silent_peer_names_the_other_framing(framer, hint):
    from mbtool.codec.data_access import ReadHoldingRegisters
    from mbtool.codec.framing import make_framer
    from mbtool.errors import NoResponse
    from mbtool.link.client import Client
    from mbtool.link.transport import SerialSettings, open_transport

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        link = open_transport(f"tcp://127.0.0.1:{port}", SerialSettings(), 1, framer)
        peer, _ = listener.accept()
        try:
            client = Client(link, make_framer(framer or "tcp"), timeout=0.3)
            with pytest.raises(NoResponse) as failure:
                client.execute(1, ReadHoldingRegisters(0, 1))
            if hint is None:
                assert str(failure.value) == "no response from unit 1 within 0.3 s"
            else:
                assert str(failure.value).endswith(f"({hint})")
        finally:
            link.close()
            peer.close()


def test_input_waiting_says_whether_bytes_came_or_the_peer_hung_up_and_reads_nothing(link):
    """What the client asks after its own work while a reply was on its way: bytes that came
    meanwhile (their arrival unknown), or a hang-up, which the read that follows reports."""
    tcp, peer = link
    assert not tcp.input_waiting()
    peer.sendall(b"\x00\x01")
    deadline = time.monotonic() + 2
    while not tcp.input_waiting():
        assert time.monotonic() < deadline
    assert tcp.input_waiting(), "asking reads nothing"
    assert tcp.read(1.0) == b"\x00\x01"
    assert not tcp.input_waiting()
    peer.close()
    deadline = time.monotonic() + 2
    while not tcp.input_waiting():
        assert time.monotonic() < deadline
    with pytest.raises(ConnectionClosed):
        tcp.read(1.0)
    tcp.close()
    assert tcp.input_waiting(), "a closed link: the read that follows says what is wrong"


def test_a_name_with_several_addresses_is_connected_at_the_one_that_answers():
    """As socket.create_connection does: localhost is ::1 and 127.0.0.1 on most systems; a
    server on 127.0.0.1 alone is reached whichever comes first."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        tcp = TcpTransport("localhost", listener.getsockname()[1], timeout=2)
        peer, _ = listener.accept()
    try:
        tcp.write(b"\x00\x01")
        assert peer.recv(2) == b"\x00\x01"
    finally:
        tcp.close()
        peer.close()


def test_no_connection_is_a_connection_failure_with_the_reason():
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]  # bound, not listening: refused
        with pytest.raises(ConnectionFailed, match=f"cannot connect to 127.0.0.1:{port}: Connection refused"):
            TcpTransport("127.0.0.1", port, timeout=2)


def test_a_transaction_s_write_and_read_are_no_socket_method_calls(link):
    """A poll's request and reply go through os.write and os.read on the socket's descriptor
    (POSIX): socket's send, sendall and recv parse their arguments by PyArg_ParseTuple, some
    300 instructions a call (callgrind), two calls a poll (issue 41.9)."""
    tcp, peer = link
    called: list = []

    def profile(frame, event, arg):
        if event == "c_call":
            called.append(arg)

    sys.setprofile(profile)
    try:
        tcp.write(b"\x00\x01request")
        asked = peer.recv(100)
        peer.sendall(b"\x00\x01reply")
        replied = tcp.read(1.0)
    finally:
        sys.setprofile(None)
    assert (asked, replied) == (b"\x00\x01request", b"\x00\x01reply")
    socket_methods = [f.__name__ for f in called if getattr(f, "__self__", None) is tcp.sock]
    assert not {"send", "sendall", "recv"} & set(socket_methods), socket_methods
    tcp.close()
    with pytest.raises(ConnectionClosed):  # a closed link reads no descriptor another file took
        tcp.read(1.0)


def test_a_read_takes_a_frame_s_worth_until_one_fills_it_then_big_chunks(link):
    """A reply is at most a frame (260 bytes over MBAP), which a read of that size takes at the
    allocator's small cost, where a 64 KiB buffer made and cut down cost some 600 instructions
    a poll; bytes coming faster than replies (a flood) fill it, and the reads that follow take
    READ_CHUNK at once, until one comes up short again."""
    tcp, peer = link
    flood = bytes(range(256)) * 800  # 200 KiB of garbage, at once
    peer.sendall(flood)
    time.sleep(0.05)
    sizes = []
    got = b""
    while len(got) < len(flood):
        data = tcp.read(1.0)
        sizes.append(len(data))
        got += data
    assert got == flood
    assert sizes[0] == base.FRAME_CHUNK
    assert len(sizes) <= 1 + len(flood) // transport.READ_CHUNK + 2, sizes  # big chunks after the first
    peer.sendall(b"\x00\x01" * 200)  # 400 bytes: after the flood's short last read, a frame's worth
    time.sleep(0.05)
    assert len(tcp.read(1.0)) == base.FRAME_CHUNK


def _tcp_unspecialized() -> list[str]:
    """The attribute reads of the TCP transport's a poll's write and read left generic (run in
    a fresh interpreter), against a peer that answers each request at once."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        tcp = TcpTransport(*listener.getsockname(), timeout=2)
        peer, _ = listener.accept()

    def answer() -> None:
        while request := peer.recv(100):
            peer.sendall(request)

    threading.Thread(target=answer, daemon=True).start()

    def transaction() -> None:
        tcp.write(b"\x00\x01request")
        assert tcp.read(1.0) == b"\x00\x01request"

    try:
        return unspecialized(transaction, str(Path(transport.__file__).parent))
    finally:
        tcp.close()
        peer.close()


@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="what is specialized is 3.11's")
def test_every_attribute_a_transaction_s_write_and_read_read_is_one_the_interpreter_specializes():
    """os.write and os.read, bound to the descriptor, were called as methods of the transport
    (an instance's attribute, looked up the generic way): two generic reads a poll."""
    assert in_fresh_interpreter("link.test_tcp_transport", "_tcp_unspecialized") == []
